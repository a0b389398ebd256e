"""The separation filter's cost for 12 drones (the demo's fleet): the joint solve that one receive thread runs
once per setpoint period, the closed-form fallback, commands that pass unchanged, and the per-setpoint
lookup every other drone's thread does (``JointFilter.command`` on a fresh cache).

Run for real with ``.venv/bin/python -m pytest tests/benchmarks/test_bench_separation.py --benchmark-enable``.
"""
from __future__ import annotations

import numpy as np
import pytest

from groundstation.separation import JointFilter, Limits, Snapshot, filter_velocities

N = 12
LIM = Limits(min_distance=0.35, period=0.05, max_decel=2.0, max_speed=1.5, latency=0.1)


def _state(spread: float, seed: int = 0):
    """12 drones on a jittered grid ``spread`` m apart, every one commanded at a random other drone."""
    rng = np.random.default_rng(seed)
    grid = np.array([[x, y] for x in range(4) for y in range(3)], dtype=float) * spread
    pos = grid - grid.mean(0) + rng.uniform(-0.05, 0.05, (N, 2))
    aim = (np.arange(N) + rng.integers(1, N, N)) % N
    want = pos[aim] - pos
    want *= (1.0 / np.linalg.norm(want, axis=1))[:, None]
    vel = want * 0.3
    return pos, vel, want, np.ones(N, dtype=bool), vel.copy()


@pytest.mark.parametrize("case", ["joint_qp", "pairwise_fallback", "unchanged"])
def test_bench_filter_12_drones(benchmark, case):
    pos, vel, want, ctrl, prev = _state(0.6 if case != "unchanged" else 3.0)
    if case == "unchanged":
        want, vel, prev = want * 0.05, vel * 0, prev * 0
    res = benchmark(filter_velocities, pos, vel, want, ctrl, LIM, prev, case != "pairwise_fallback")
    assert res.method == {"joint_qp": "qp", "pairwise_fallback": "pairwise", "unchanged": "unchanged"}[case]
    benchmark.extra_info["drones"] = N


def test_bench_cached_lookup(benchmark):
    pos, vel, want, ctrl, prev = _state(0.6)
    snap = Snapshot([f"cf{i}" for i in range(N)], pos, vel, want, ctrl, prev)
    jf = JointFilter(LIM, lambda: snap, interval=1e9)  # never stale: what 11 of 12 setpoints cost
    jf.command("cf0", now=0.0)
    v = benchmark(jf.command, "cf5", 1.0)
    assert v.shape == (2,) and jf.stats()["solves"] == 1
