"""Bounded Voronoi areas per env step: the numba kernel batched, and scipy's mirrored-points Voronoi for scale.

Run for real with ``.venv/bin/python -m pytest tests/benchmarks/test_bench_voronoi.py --benchmark-enable``;
``extra_info["per_env_us"]`` is the median divided by the batch size.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import Voronoi

from training.voronoi import bounded_cell_areas, bounded_cells

HW = 3.0
N_SEEDS = 12  # 5 pursuers + 5 scouts + 2 evaders, every agent a seed


def _points(b: int) -> np.ndarray:
    return np.random.default_rng(b).uniform(-HW, HW, (b, N_SEEDS, 2))


def _record(benchmark, b: int) -> None:
    if benchmark.stats is not None:  # None under --benchmark-disable, where the function runs once
        benchmark.extra_info["per_env_us"] = benchmark.stats.stats.median / b * 1e6
    benchmark.extra_info["batch"] = b
    benchmark.extra_info["seeds"] = N_SEEDS


def scipy_mirrored_areas(pts: np.ndarray, hw: float) -> np.ndarray:
    """Areas of one env's clipped cells from scipy's Voronoi of the points and their mirrors in the 4 edges."""
    n = len(pts)
    mirrors = [pts]
    for axis in (0, 1):
        for wall in (-hw, hw):
            m = pts.copy()
            m[:, axis] = 2 * wall - m[:, axis]
            mirrors.append(m)
    vor = Voronoi(np.concatenate(mirrors))
    areas = np.empty(n)
    for i in range(n):
        v = vor.vertices[vor.regions[vor.point_region[i]]]
        v = v[np.argsort(np.arctan2(*(v - v.mean(0)).T[::-1]))]
        x, y = v.T
        areas[i] = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
    return areas


@pytest.mark.parametrize("b", [1, 256, 1024])
def test_bench_bounded_cell_areas(benchmark, b):
    pts = _points(b)
    bounded_cell_areas(pts, HW)  # numba compile or cache load, outside the timed part
    areas = benchmark(bounded_cell_areas, pts, HW)
    _record(benchmark, b)
    np.testing.assert_allclose(areas.sum(-1), (2 * HW) ** 2, rtol=1e-9)


def test_bench_bounded_cells_with_centroids(benchmark):
    b = 1024
    pts = _points(b)
    bounded_cells(pts, HW)
    areas, cents = benchmark(bounded_cells, pts, HW)
    _record(benchmark, b)
    np.testing.assert_allclose(areas.sum(-1), (2 * HW) ** 2, rtol=1e-9)
    assert cents.shape == (b, N_SEEDS, 2)


def test_bench_scipy_mirrored_reference(benchmark):
    pts = _points(1)
    areas = benchmark(scipy_mirrored_areas, pts[0], HW)
    _record(benchmark, 1)
    np.testing.assert_allclose(areas, bounded_cell_areas(pts, HW)[0], atol=1e-9)
