"""The one convex clip (``runtime.geometry``) against shapely, and its users."""
from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import Polygon

from groundstation.fence import FenceConfig
from runtime.geometry import clip_convex


def _half_plane(n: np.ndarray, c: float, big: float = 1e3) -> Polygon:
    """{x : n . x <= c} as a huge rectangle."""
    u = n / np.linalg.norm(n)
    t = np.array([-u[1], u[0]])
    m = u * c / np.linalg.norm(n)
    return Polygon([m + big * t, m - big * t, m - big * t - big * u, m + big * t - big * u])


@pytest.mark.parametrize("seed", range(8))
def test_clip_convex_matches_shapely(seed):
    rng = np.random.default_rng(seed)
    k = rng.integers(3, 9)
    ang = np.sort(rng.uniform(0, 2 * np.pi, k))
    poly = np.stack([np.cos(ang), np.sin(ang)], axis=1) * rng.uniform(0.5, 2.0) + rng.normal(size=2)
    for _ in range(5):
        n = rng.normal(size=2)
        c = float(n @ poly.mean(axis=0) + rng.normal() * 0.5)
        got = clip_convex(poly, n, c)
        ref = Polygon(poly).intersection(_half_plane(n, c))
        if len(got) < 3:
            assert ref.area < 1e-12
        else:
            assert Polygon(got).symmetric_difference(ref).area < 1e-12


def test_clip_edge_cases():
    sq = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert np.array_equal(clip_convex(sq, np.array([1.0, 0.0]), 2.0), sq)  # all inside: unchanged
    assert clip_convex(sq, np.array([1.0, 0.0]), -1.0).shape == (0, 2)  # all outside: empty
    on = clip_convex(sq, np.array([1.0, 0.0]), 1.0)  # an edge on the line: kept once, not doubled
    assert len(on) == 4
    half = clip_convex(sq, np.array([1.0, 0.0]), 0.5)
    assert Polygon(half).area == pytest.approx(0.5)
    assert clip_convex(np.zeros((0, 2)), np.array([1.0, 0.0]), 0.0).shape == (0, 2)


def test_the_fence_s_safe_polygon_is_its_polygon_shrunk_by_the_margin():
    fence = FenceConfig(vertices=((-3.0, -2.0), (0.0, -3.5), (3.0, -2.0), (2.5, 2.5), (-2.0, 3.0)), margin=0.3)
    ref = Polygon(fence.polygon).buffer(-0.3, join_style=2)  # mitred: the half-planes moved in
    assert Polygon(fence.safe_polygon).symmetric_difference(ref).area < 1e-9
