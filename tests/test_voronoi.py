"""Exact bounded Voronoi cells: differential tests against shapely and scipy, degenerate inputs, properties."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Voronoi
from shapely.geometry import Polygon, box

from training.voronoi import bounded_cell_areas, bounded_cell_polygons, bounded_cells

HW = 3.0
SQUARE = (2 * HW) ** 2


def shapely_cells(pts: np.ndarray, hw: float) -> tuple[np.ndarray, np.ndarray]:
    """Reference for one env ``[N, 2]``: the square intersected with every bisector half-plane, by shapely.

    Same coincident-point convention as the module: exact duplicates share their cell equally.
    """
    n = len(pts)
    areas = np.zeros(n)
    cents = np.zeros((n, 2))
    big = 100.0 * (hw + np.abs(pts).max())
    for i in range(n):
        cell = box(-hw, -hw, hw, hw)
        mult = 1
        for j in range(n):
            if j == i:
                continue
            d = pts[j] - pts[i]
            if not d.any():
                mult += 1
                continue
            nrm = d / np.hypot(*d)
            tan = np.array([-nrm[1], nrm[0]])
            mid = 0.5 * (pts[i] + pts[j])
            # {x : nrm . x <= nrm . mid}, as a rectangle far larger than the square
            half_plane = Polygon([mid + big * tan, mid - big * tan, mid - big * tan - big * nrm,
                                  mid + big * tan - big * nrm])
            cell = cell.intersection(half_plane)
        if cell.area > 0:
            areas[i] = cell.area / mult
            cents[i] = (cell.centroid.x, cell.centroid.y)
        else:
            cents[i] = np.clip(pts[i], -hw, hw)
    return areas, cents


def scipy_mirrored_cells(pts: np.ndarray, hw: float) -> tuple[np.ndarray, np.ndarray]:
    """Reference for one env of distinct interior points: scipy's Voronoi of the points and their 4 mirrors.

    Mirroring across the square's edges makes every original cell bounded and exactly the clipped cell.
    """
    n = len(pts)
    mirrors = [pts]
    for axis in (0, 1):
        for wall in (-hw, hw):
            m = pts.copy()
            m[:, axis] = 2 * wall - m[:, axis]
            mirrors.append(m)
    vor = Voronoi(np.concatenate(mirrors))
    areas = np.zeros(n)
    cents = np.zeros((n, 2))
    for i in range(n):
        region = vor.regions[vor.point_region[i]]
        assert -1 not in region
        v = vor.vertices[region]
        v = v[np.argsort(np.arctan2(*(v - v.mean(0)).T[::-1]))]  # CCW around an interior point
        areas[i], cents[i] = polygon_area_centroid(v)
    return areas, cents


def polygon_area_centroid(v: np.ndarray) -> tuple[float, np.ndarray]:
    x, y = (v - v[0]).T
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cr = x * yn - xn * y
    a2 = cr.sum()
    return 0.5 * a2, v[0] + np.array([((x + xn) * cr).sum(), ((y + yn) * cr).sum()]) / (3 * a2)


def assert_matches(pts: np.ndarray, areas: np.ndarray, cents: np.ndarray, tol: float = 1e-9) -> None:
    for b in range(len(pts)):
        ref_a, ref_c = shapely_cells(pts[b], HW)
        np.testing.assert_allclose(areas[b], ref_a, rtol=0, atol=tol, err_msg=f"areas, env {b}")
        np.testing.assert_allclose(cents[b], ref_c, rtol=0, atol=tol, err_msg=f"centroids, env {b}")


def assert_partition(areas: np.ndarray, cents: np.ndarray, hw: float = HW) -> None:
    side2 = (2 * hw) ** 2
    np.testing.assert_allclose(areas.sum(-1), side2, rtol=1e-9, atol=0)
    assert (areas >= 0).all()
    assert (np.abs(cents) <= hw).all()
    # The area-weighted centroids of a partition add up to the square's own moment, which is zero.
    np.testing.assert_allclose((areas[..., None] * cents).sum(-2), 0.0, atol=1e-9 * side2 * hw)


@pytest.mark.parametrize("n", range(1, 21))
def test_random_points_match_shapely(n):
    rng = np.random.default_rng(100 + n)
    pts = rng.uniform(-HW, HW, (3, n, 2))
    areas, cents = bounded_cells(pts, HW)
    assert areas.shape == (3, n) and cents.shape == (3, n, 2)
    assert areas.dtype == np.float64 and cents.dtype == np.float64
    assert_matches(pts, areas, cents)
    assert_partition(areas, cents)
    np.testing.assert_array_equal(bounded_cell_areas(pts, HW), areas)


@pytest.mark.parametrize("b", [1, 2, 11, 40])
def test_batch_sizes_match_per_env_calls_and_shapely(b):
    # b = 40 with N = 12 is 480 cells, which takes the parallel kernel; every env must equal its lone call.
    rng = np.random.default_rng(b)
    pts = rng.uniform(-HW, HW, (b, 12, 2))
    areas, cents = bounded_cells(pts, HW)
    for k in range(b):
        a1, c1 = bounded_cells(pts[k:k + 1], HW)
        np.testing.assert_array_equal(a1[0], areas[k])
        np.testing.assert_array_equal(c1[0], cents[k])
    assert_matches(pts[:3], areas[:3], cents[:3])
    assert_partition(areas, cents)


@pytest.mark.parametrize("n,seed", [(3, 0), (5, 1), (12, 2), (20, 3)])
def test_random_points_match_scipy_mirrored(n, seed):
    pts = np.random.default_rng(seed).uniform(-0.95 * HW, 0.95 * HW, (1, n, 2))
    areas, cents = bounded_cells(pts, HW)
    ref_a, ref_c = scipy_mirrored_cells(pts[0], HW)
    np.testing.assert_allclose(areas[0], ref_a, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cents[0], ref_c, rtol=0, atol=1e-9)


def test_other_half_width_matches_shapely():
    hw = 0.75
    pts = np.random.default_rng(7).uniform(-hw, hw, (2, 9, 2))
    areas, cents = bounded_cells(pts, hw)
    for b in range(2):
        ref_a, ref_c = shapely_cells(pts[b], hw)
        np.testing.assert_allclose(areas[b], ref_a, atol=1e-12)
        np.testing.assert_allclose(cents[b], ref_c, atol=1e-12)
    assert_partition(areas, cents, hw)


def test_single_point_gets_whole_square_wherever_it_is():
    pts = np.array([[[0.3, -2.0]], [[3.0, 3.0]], [[-3.5, 0.0]]])
    areas, cents = bounded_cells(pts, HW)
    np.testing.assert_array_equal(areas, SQUARE)
    np.testing.assert_allclose(cents, 0.0, atol=1e-15)


def test_two_points_split_along_bisector():
    areas, cents = bounded_cells(np.array([[[-1.0, 0.0], [1.0, 0.0]], [[0.0, -2.0], [0.0, 1.0]]]), HW)
    np.testing.assert_allclose(areas[0], [18.0, 18.0])
    np.testing.assert_allclose(cents[0], [[-1.5, 0.0], [1.5, 0.0]], atol=1e-15)
    # bisector y = -0.5: strips of height 2.5 and 3.5
    np.testing.assert_allclose(areas[1], [15.0, 21.0])
    np.testing.assert_allclose(cents[1], [[0.0, -1.75], [0.0, 1.25]], atol=1e-15)
    pts = np.random.default_rng(2).uniform(-HW, HW, (4, 2, 2))
    assert_matches(pts, *bounded_cells(pts, HW))


def test_coincident_points_share_their_cell_equally():
    rng = np.random.default_rng(5)
    base = rng.uniform(-HW, HW, (6, 2))
    # point 0 twice more (a triple), point 3 once more (a pair)
    dup = np.concatenate([base, base[[0, 0, 3]]])
    a_base, c_base = bounded_cells(base[None], HW)
    a_dup, c_dup = bounded_cells(dup[None], HW)
    for idx, members in ((0, [0, 6, 7]), (3, [3, 8])):
        np.testing.assert_allclose(a_dup[0, members], a_base[0, idx] / len(members), atol=1e-12)
        np.testing.assert_allclose(c_dup[0, members], np.broadcast_to(c_base[0, idx], (len(members), 2)),
                                   atol=1e-12)
    for k in (1, 2, 4, 5):
        np.testing.assert_allclose(a_dup[0, k], a_base[0, k], atol=1e-12)
    assert_matches(dup[None], a_dup, c_dup)
    assert_partition(a_dup, c_dup)


def test_all_points_identical_split_the_square():
    for n in (2, 3, 12):
        areas, cents = bounded_cells(np.full((1, n, 2), 1.25), HW)
        np.testing.assert_allclose(areas, SQUARE / n, rtol=1e-15)
        np.testing.assert_allclose(cents, 0.0, atol=1e-15)


def test_collinear_points_give_strips():
    xs = np.array([-2.0, 0.0, 1.0])
    # strip edges at x = -1 and x = 0.5
    want_areas = np.array([2.0, 1.5, 2.5]) * 6.0
    want_mid = np.array([-2.0, -0.25, 1.75])
    horizontal = np.stack([xs, np.full(3, 0.5)], -1)
    vertical = horizontal[:, ::-1]
    areas, cents = bounded_cells(np.stack([horizontal, vertical]), HW)
    np.testing.assert_allclose(areas, [want_areas, want_areas], rtol=1e-15)
    np.testing.assert_allclose(cents[0], np.stack([want_mid, np.zeros(3)], -1), atol=1e-15)
    np.testing.assert_allclose(cents[1], np.stack([np.zeros(3), want_mid], -1), atol=1e-15)


def test_diagonal_collinear_points_are_symmetric_about_the_diagonal():
    t = np.array([-2.5, -1.0, 0.2, 0.4, 2.9])
    pts = np.stack([t, t], -1)[None]
    areas, cents = bounded_cells(pts, HW)
    np.testing.assert_allclose(cents[0, :, 0], cents[0, :, 1], atol=1e-12)
    assert_matches(pts, areas, cents)
    assert_partition(areas, cents)


def test_points_on_corners_and_edges():
    corners = np.array([[-HW, -HW], [HW, -HW], [HW, HW], [-HW, HW]])
    areas, cents = bounded_cells(corners[None], HW)
    np.testing.assert_allclose(areas, 9.0, rtol=1e-15)
    np.testing.assert_allclose(cents[0], corners / 2, atol=1e-15)
    edges = np.array([[-HW, 0.0], [HW, 0.0]])
    areas, cents = bounded_cells(edges[None], HW)
    np.testing.assert_allclose(areas, 18.0, rtol=1e-15)
    rng = np.random.default_rng(9)
    pts = rng.uniform(-HW, HW, (5, 8, 2))
    pts[:, :4, 0] = rng.choice([-HW, HW], (5, 4))  # half the points on a vertical edge
    pts[:, 4:6] = rng.choice([-HW, HW], (5, 2, 2))  # two on corners (sometimes the same one)
    areas, cents = bounded_cells(pts, HW)
    assert_matches(pts, areas, cents)
    assert_partition(areas, cents)


def test_points_outside_the_square_still_partition_it():
    rng = np.random.default_rng(11)
    pts = rng.uniform(-1.2 * HW, 1.2 * HW, (6, 7, 2))
    areas, cents = bounded_cells(pts, HW)
    assert_matches(pts, areas, cents)
    assert_partition(areas, cents)
    # a point beyond its bisector's reach gets nothing, its centroid is itself clamped to the square
    areas, cents = bounded_cells(np.array([[[0.0, 0.0], [10.0, 1.0]]]), HW)
    np.testing.assert_array_equal(areas, [[SQUARE, 0.0]])
    np.testing.assert_array_equal(cents[0, 1], [HW, 1.0])


def test_nearly_coincident_points_stay_consistent():
    # a subnormal separation: the bisector is still exact enough for the cells to tile the square
    pts = np.array([[[0.0, 0.0], [5e-324, 0.0], [0.0, 1e-320]], [[1.0, 1.0], [1.0 + 2e-16, 1.0], [-2.0, 0.5]]])
    areas, cents = bounded_cells(pts, HW)
    assert_partition(areas, cents)
    np.testing.assert_allclose(areas[0, 0], 9.0, atol=1e-12)


def test_float32_and_integer_input_are_converted():
    pts32 = np.random.default_rng(3).uniform(-HW, HW, (2, 6, 2)).astype(np.float32)
    a32, c32 = bounded_cells(pts32, np.float32(HW))
    a64, c64 = bounded_cells(pts32.astype(np.float64), HW)
    assert a32.dtype == np.float64 and c32.dtype == np.float64
    np.testing.assert_array_equal(a32, a64)
    np.testing.assert_array_equal(c32, c64)
    areas = bounded_cell_areas([[[-1, 0], [1, 0]]], 3)
    np.testing.assert_allclose(areas, [[18.0, 18.0]])


def test_empty_batch():
    areas, cents = bounded_cells(np.zeros((0, 4, 2)), HW)
    assert areas.shape == (0, 4) and cents.shape == (0, 4, 2)


@settings(max_examples=300, deadline=None)
@given(st.integers(1, 3).flatmap(lambda b: st.integers(1, 12).flatmap(lambda n: st.lists(
    st.lists(st.tuples(st.floats(-HW, HW), st.floats(-HW, HW)), min_size=n, max_size=n),
    min_size=b, max_size=b))))
def test_property_cells_partition_the_square(envs):
    pts = np.array(envs, dtype=np.float64)
    areas, cents = bounded_cells(pts, HW)
    assert_partition(areas, cents)
    np.testing.assert_array_equal(bounded_cell_areas(pts, HW), areas)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([-HW, -1.0, 0.0, 0.5, HW]), st.sampled_from([-HW, 0.0, 2.0, HW])),
                min_size=1, max_size=10))
def test_property_grid_points_with_duplicates_and_collinearity(pts):
    # a coarse grid makes coincident, collinear and cocircular points the rule rather than the exception
    arr = np.array(pts)[None]
    areas, cents = bounded_cells(arr, HW)
    assert_partition(areas, cents)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("b", [1, 50])
def test_non_finite_points_raise(bad, b):
    pts = np.zeros((b, 12, 2))
    pts[-1, 7, 1] = bad
    with pytest.raises(ValueError, match="points"):
        bounded_cells(pts, HW)
    with pytest.raises(ValueError, match="points"):
        bounded_cell_areas(pts, HW)


@pytest.mark.parametrize("hw", [np.nan, np.inf, 0.0, -1.0])
def test_bad_half_width_values_raise(hw):
    with pytest.raises(ValueError, match="half_width"):
        bounded_cells(np.zeros((1, 2, 2)), hw)


@pytest.mark.parametrize("hw", ["3", None, True, 1 + 2j])
def test_bad_half_width_types_raise(hw):
    with pytest.raises(TypeError, match="half_width"):
        bounded_cell_areas(np.zeros((1, 2, 2)), hw)


@pytest.mark.parametrize("shape", [(12, 2), (1, 12, 3), (1, 12), (2, 0, 2), (1, 1, 1, 2)])
def test_bad_shapes_raise(shape):
    with pytest.raises(ValueError, match="points"):
        bounded_cells(np.zeros(shape), HW)


@pytest.mark.parametrize("pts", [np.zeros((1, 2, 2), dtype=complex), np.array([[["a", "b"]]]),
                                 np.zeros((1, 2, 2), dtype=bool)])
def test_bad_dtypes_raise(pts):
    with pytest.raises(TypeError, match="points"):
        bounded_cells(pts, HW)


def shapely_cell_polygons(pts: np.ndarray, hw: float) -> list:
    """Reference cells of one env as shapely polygons (each coincident copy gets the whole shared cell)."""
    big = 100.0 * (hw + np.abs(pts).max())
    out = []
    for i in range(len(pts)):
        cell = box(-hw, -hw, hw, hw)
        for j in range(len(pts)):
            d = pts[j] - pts[i]
            if j == i or not d.any():
                continue
            nrm = d / np.hypot(*d)
            tan = np.array([-nrm[1], nrm[0]])
            mid = 0.5 * (pts[i] + pts[j])
            cell = cell.intersection(Polygon([mid + big * tan, mid - big * tan, mid - big * tan - big * nrm,
                                              mid + big * tan - big * nrm]))
        out.append(cell)
    return out


@pytest.mark.parametrize("n, seed", [(1, 0), (2, 1), (12, 2), (12, 3), (25, 4)])
def test_cell_polygons_are_shapely_s_cells_and_the_kernel_s_areas(n, seed):
    """The drawn cells (``bounded_cell_polygons``, the kernel's own clipping) cover exactly shapely's cells, CCW,
    with the kernel's areas."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-HW, HW, (n, 2))
    if n > 3:
        pts[1] = pts[0]  # a coincident pair
    polys = bounded_cell_polygons(pts, HW)
    ref = shapely_cell_polygons(pts, HW)
    areas = bounded_cell_areas(pts[None], HW)[0]
    mult = np.array([sum(np.array_equal(p, q) for q in pts) for p in pts])
    for poly, cell, area, m in zip(polys, ref, areas, mult):
        mine = Polygon(poly)
        assert mine.is_valid and mine.exterior.is_ccw
        assert mine.symmetric_difference(cell).area < 1e-12
        assert mine.area / m == pytest.approx(area, abs=1e-12)
