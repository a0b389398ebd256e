"""The compiled geofence geometry (``groundstation.fence_geometry``) against the numpy code it replaced
(``fence_reference``: the same decisions, the same numbers to rounding) and against shapely (an independent model
of the safe set), on random fences and points."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

import fence_reference as ref
from fence_strategies import fences, point, sane_point
from groundstation import fence as gsfence
from groundstation import safety
from groundstation.safety import FenceConfig, FenceStatus, KeepOut

EQUAL = settings(max_examples=300, deadline=None)
"""Random seeds (``HYPOTHESIS_PROFILE=search``, with ``--hypothesis-seed=N`` to repeat one; the suite's own runs are
derandomized, tests/conftest.py) found kernel and reference apart at degenerate ties, each now recognised: a point on
a threshold (``_tie``), several nearest safe points (``_as_near``; a velocity limit from outside heads for either),
a ray along a keep-out's tangent (``_grazes``), a ray at a grazing angle from a point within rounding of a
boundary."""
unit = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(lambda u: np.linalg.norm(u) > 1e-3)
near = st.floats(-1e-9, 1e-9)  # nudges onto and just off a boundary


ROUNDING = 1e-12
"""[m, m/s] How far a position or velocity of the kernel may be from the reference's: rounding. The kernel's scalar
sums and numpy's vectorized products (SIMD loops and BLAS, whose paths and last bits differ between releases and
machines) need not agree to the bit: on a fresh install of 2026-12-03 (numpy 2.4.6, numba 0.68.1) the reference gave
-1.1e-17 m/s where the kernel gave 0, and clamped points 2.7e-15 m apart. Every decision (a status, a flag, which
constraint binds) must agree, except at a tie."""


def _same(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_array_equal(a, b)  # unchanged inputs: to the bit


def _agree(fence: FenceConfig, p: object, got: object, want: object) -> None:
    """``got`` is ``want``: a status or a flag exactly, a position or a velocity to ``ROUNDING``; unless ``p`` is a
    tie (``_tie``), where a decision may go either way."""
    if isinstance(got, np.ndarray) and isinstance(want, np.ndarray):
        if np.array_equal(got, want):
            return
        if got.shape == want.shape and np.allclose(got, want, rtol=0.0, atol=ROUNDING):
            event("differs within rounding")
            return
    elif got == want:
        return
    assert _tie(fence, p), (p, got, want)
    event("differs, within rounding of a threshold")


def _as_near(fence: FenceConfig, p: object, got: np.ndarray, want: np.ndarray) -> bool:
    """Whether ``got`` and ``want`` (each side's ``clamp_position(p)``) differ beyond rounding but are both nearest
    points of the safe set: in it (to 1e-9) and as far from ``p`` to rounding. A point with several nearest points
    (a keep-out circle's centre, or the middle of a symmetric fence) may get any of them: hypothesis found kernel
    and reference going opposite ways from such points, as their last bits decided."""
    a = gsfence.as_point(p)
    if a is None or np.allclose(got, want, rtol=0.0, atol=ROUNDING):
        return False
    g = gsfence.geometry(fence)
    a[:2] = np.clip(a[:2], g.lo, g.hi)
    return bool(abs(np.linalg.norm(got - a) - np.linalg.norm(want - a)) <= 1e-9
                and gsfence.in_safe_set(fence, got, 1e-9) and ref.in_safe_set(fence, want.copy(), 1e-9))


def _agree_clamp(fence: FenceConfig, p: object, got: np.ndarray, want: np.ndarray) -> None:
    """``clamp_position``'s answers agree as ``_agree`` asks, or are both nearest points (``_as_near``)."""
    if _as_near(fence, p, got, want):
        event("another nearest point, as near")
        return
    _agree(fence, p, got, want)


def _tie(fence: FenceConfig, p: object) -> bool:
    """Whether ``p`` lies within rounding (1e-12 m) of a threshold that decides where it is: a polygon's edge
    or a circle, exactly or at the ``TOL`` slack. There the reference's ``normals @ xy`` (a BLAS product that
    may fuse a multiply-add) and the kernel's ``nx * x + ny * y`` can round to different sides (found by
    hypothesis at a corner of a polygon fence: OUTSIDE vs MARGIN), and every answer that follows may differ."""
    a = gsfence.as_point(p)
    if a is None:
        return False
    g = gsfence.geometry(fence)
    xy = np.clip(a[:2], g.lo, g.hi)
    gaps = [g.normals @ xy - g.offsets, g.inner_normals @ xy - g.inner_offsets,
            np.hypot(*(xy - g.centres).T) - g.radii, np.hypot(*(xy - g.centres).T) - g.grown]
    gaps = np.concatenate([np.ravel(x) for x in gaps])
    return bool(np.any(np.abs(np.concatenate([gaps, gaps + gsfence.TOL, gaps - gsfence.TOL])) <= 1e-12))


def _grazes(fence: FenceConfig, s: np.ndarray, u: np.ndarray) -> list[float]:
    """Distances along the unit ray ``s + t u`` (t >= 0) to where it touches a keep-out circle (its radius or its
    grown radius) within rounding of a tangent: there an intersection's discriminant is within rounding of zero, and
    kernel and reference may see a touch or a miss (found by hypothesis: a ray along x = 0.75 past a circle of
    radius 0.75 at x = 0)."""
    g = gsfence.geometry(fence)
    h = np.array(u[:2], dtype=float)
    hn = float(np.linalg.norm(h))
    if hn < 1e-9:
        return []
    out = []
    for c, radii in zip(g.centres, zip(g.radii, g.grown)):
        d = c - s[:2]
        along = float(d @ h) / hn  # horizontal distance to the foot of the perpendicular (along the ray: / hn)
        perp = abs(float(h[0] * d[1] - h[1] * d[0])) / hn
        out += [along / hn for r in radii if along >= 0 and abs(perp - r) <= 1e-9]
    return out


def _on_boundaries(fence: FenceConfig, draw_t: float, nudge: tuple[float, float, float]) -> np.ndarray:
    """A point on the safe polygon's edge, a grown keep-out circle or the fence polygon, nudged by ``nudge``."""
    g = gsfence.geometry(fence)
    pieces = [("inner", i) for i in range(len(g.inner))] + [("outer", i) for i in range(len(g.outer))] + \
        [("circle", i) for i in range(len(g.radii))]
    kind, i = pieces[int(draw_t * 1e6) % len(pieces)]
    t = (draw_t * 1e3) % 1.0
    if kind == "circle":
        r = g.grown[i] if int(draw_t * 1e4) % 2 else g.radii[i]
        xy = g.centres[i] + r * np.array([math.cos(2 * math.pi * t), math.sin(2 * math.pi * t)])
    else:
        poly = g.inner if kind == "inner" else g.outer
        xy = poly[i] + t * (poly[(i + 1) % len(poly)] - poly[i])
    z = (g.z_lo, g.z_hi, fence.z_min, fence.z_max)[int(draw_t * 1e5) % 4]
    return np.array([xy[0], xy[1], z]) + np.array(nudge)


@EQUAL
@given(fence=fences(), p=st.one_of(point, sane_point), fb=st.one_of(st.none(), point))
def test_position_checks_and_clamps_equal_the_reference(fence: FenceConfig, p: tuple, fb: tuple | None) -> None:
    _agree(fence, p, gsfence.check_position(fence, p), ref.check_position(fence, p))
    for tol in (0.0, 1e-9, 1e-6):
        _agree(fence, p, gsfence.in_safe_set(fence, p, tol), ref.in_safe_set(fence, p, tol))
    fb_used = p if gsfence.as_point(p) is not None else fb
    _agree_clamp(fence, fb_used, gsfence.clamp_position(fence, p, fb), ref.clamp_position(fence, p, fb))


@EQUAL
@given(fence=fences(), t=st.floats(0, 1), nudge=st.tuples(near, near, near), u=unit)
def test_points_on_the_boundaries_are_classified_and_clamped_as_the_reference(fence: FenceConfig, t: float,
                                                                               nudge: tuple, u: tuple) -> None:
    p = _on_boundaries(fence, t, nudge)
    if _tie(fence, p):
        event("within rounding of a threshold")
    _agree(fence, p, gsfence.check_position(fence, p), ref.check_position(fence, p.copy()))
    for tol in (0.0, 1e-9):
        _agree(fence, p, gsfence.in_safe_set(fence, p, tol), ref.in_safe_set(fence, p.copy(), tol))
    got, want = gsfence.clamp_position(fence, p), ref.clamp_position(fence, p.copy())
    _agree_clamp(fence, p, got, want)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    w = np.array(u) * 2.0
    _agree(fence, p, safety.limit_velocity(fence, p, w, 0.1), ref.limit_velocity(fence, p.copy(), w, 0.1))


@EQUAL
@given(fence=fences(), p=st.one_of(point, sane_point), v=st.one_of(point, st.tuples(*[st.floats(-3, 3)] * 3)),
       dt=st.one_of(st.floats(0.0, 0.5), st.sampled_from([math.nan, -0.1, math.inf, 0.0])))
def test_velocity_limits_equal_the_reference(fence: FenceConfig, p: tuple, v: tuple, dt: float) -> None:
    got, want = safety.limit_velocity(fence, p, v, dt), ref.limit_velocity(fence, p, v, dt)
    near = gsfence.clamp_position(fence, p), ref.clamp_position(fence, p)
    if _as_near(fence, p, *near):
        # outside the safe set with several nearest points: each side keeps the part of v that heads for its own
        a = gsfence.as_point(p)
        for w, q in zip((got, want), near):
            assert np.linalg.norm(w) <= fence.max_speed + 1e-12 and w @ (q - a) >= -ROUNDING, (w, q)
        event("outside, another nearest point to head for")
        return
    _agree(fence, p, got, want)


@EQUAL
@given(fence=fences(), p=sane_point, u=unit, target=st.one_of(point, sane_point))
def test_free_distance_and_paths_equal_the_reference(fence: FenceConfig, p: tuple, u: tuple, target: tuple) -> None:
    s = gsfence.clamp_position(fence, p)
    uu = np.array(u) / np.linalg.norm(u)
    got, want = safety.free_distance(fence, s, uu), ref.free_distance(fence, s, uu)
    if not (got == want or abs(got - want) <= ROUNDING * max(1.0, abs(want))):
        if _tie(fence, s):
            # from a point within rounding of a boundary, a ray that crosses it at a grazing angle leaves within
            # rounding / its horizontal component (found: u = (1.4e-10, 0, 1) from a polygon's edge, 1.5 and 2.9 um)
            assert abs(got - want) <= ROUNDING / max(math.hypot(uu[0], uu[1]), 1e-12), (got, want)
            event("a ray from a point on a boundary, within rounding")
        else:
            # a ray within rounding of a keep-out's tangent: one side stops at the tangent point, the other flies on
            assert any(abs(min(got, want) - t) <= 1e-6 for t in _grazes(fence, s, uu)), (got, want)
            event("a ray that grazes a keep-out")
    got, want = safety.clamp_path(fence, p, target), ref.clamp_path(fence, p, target)
    ties = [(fence, x, gsfence.clamp_position(fence, x), ref.clamp_position(fence, x)) for x in (target, p)]
    if any(_as_near(*t) for t in ties):  # the path starts or ends at another nearest point: its own path
        assert gsfence.in_safe_set(fence, got, 1e-9) and ref.in_safe_set(fence, want.copy(), 1e-9), (got, want)
        event("a path from or to another nearest point")
    else:
        _agree(fence, p, got, want)
    for d, dt, a, c in ((0.3, 0.1, 2.0, 2.0), (math.inf, 0.1, 2.0, 0.0), (-1.0, 0.1, 2.0, 2.0)):
        assert safety.max_safe_speed(d, dt, a, c) == ref.max_safe_speed(d, dt, a, c)


def test_the_setpoint_path_arrays_are_used_as_given_and_never_changed() -> None:
    """The hot path passes float64 [3] arrays straight to the kernels (no copy); they must stay unchanged (the
    numpy code clipped a far-out position in place, in the caller's array)."""
    f = FenceConfig(keep_out=(KeepOut(1.0, 0.0, 0.3),))
    p, v = np.array([1e9, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    before = p.copy(), v.copy()
    safety.limit_velocity(f, p, v, 0.1)
    gsfence.clamp_position(f, p)
    _same(p, before[0])
    _same(v, before[1])
    for bad in (np.array([np.nan, 0.0, 1.0]), np.array([np.inf, -np.inf, 1.0]), np.array([0, 0, 1], dtype=np.int64),
                np.array([0.0, 0.0, 1.0], dtype=np.float32), np.zeros(4), [0.0, 0.0], "abc", None):
        _same(safety.limit_velocity(f, bad, v, 0.1), ref.limit_velocity(f, bad, v, 0.1))
        assert gsfence.check_position(f, bad) is ref.check_position(f, bad)


# -- shapely, an independent model of the safe set ----------------------------------------------------------

QUAD = 256  # segments per quarter circle: the polygonal circle lies within r (1 - cos(pi / 512)) < 2e-5 r of it


def _shapely_safe(fence: FenceConfig):
    shapely = pytest.importorskip("shapely")
    from shapely.geometry import Point, Polygon
    g = gsfence.geometry(fence)
    safe = Polygon(g.inner)
    holes = [Point(c).buffer(r, quad_segs=QUAD) for c, r in zip(g.centres, g.grown)]
    return safe.difference(shapely.unary_union(holes)) if holes else safe, Point


@settings(max_examples=150, deadline=None)
@given(fence=fences(), p=sane_point)
def test_the_clamp_is_shapelys_nearest_safe_point(fence: FenceConfig, p: tuple) -> None:
    region, Point = _shapely_safe(fence)
    q = gsfence.clamp_position(fence, p)
    slack = 2e-5 * max([1.0, *gsfence.geometry(fence).grown])
    assert region.distance(Point(q[:2])) <= 1e-9 + slack  # in the set
    want = region.distance(Point(p[:2]))  # to shapely's (polygonal, slightly larger) set
    got = math.hypot(q[0] - p[0], q[1] - p[1])
    # a point within TOL of every edge it is outside of is in the set as it stands: at a corner sqrt(2) TOL away
    assert want - 2 * gsfence.TOL <= got <= want + slack, (got, want)


@settings(max_examples=150, deadline=None)
@given(fence=fences(), p=sane_point)
def test_the_safe_set_is_shapelys(fence: FenceConfig, p: tuple) -> None:
    region, Point = _shapely_safe(fence)
    d = region.boundary.distance(Point(p[:2]))
    g = gsfence.geometry(fence)
    if d < 1e-4 * max([1.0, *g.grown]) or abs(p[2] - g.z_lo) < 1e-9 or abs(p[2] - g.z_hi) < 1e-9:
        return  # too near a boundary for the polygonal circles to say
    want = region.contains(Point(p[:2])) and g.z_lo <= p[2] <= g.z_hi
    assert gsfence.in_safe_set(fence, p, 0.0) is want
    if want:
        assert gsfence.check_position(fence, p) is FenceStatus.INSIDE
