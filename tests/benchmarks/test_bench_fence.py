"""What the geofence costs per setpoint: the compiled geometry (``groundstation.fence_geometry``) beside the
numpy code it replaced (``tests/fence_reference.py``), on the shipped fence (``configs/fence.toml``: the arena,
three keep-out circles) with the setpoint path's own inputs (float64 [3] arrays).

Cases: ``gate`` is ``Geofence.filter_velocity``, what each setpoint of the demo passes (the reference swapped in
for ``check_position`` and ``limit_velocity``); ``inside`` and ``margin`` are ``limit_velocity`` from the safe set
and from the margin (the nearest-point search); ``check`` is ``check_position``; ``clamp`` is ``clamp_position``
of a target beyond the fence.

Run for real with ``.venv/bin/python -m pytest tests/benchmarks/test_bench_fence.py --benchmark-enable``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import fence_reference as ref
from groundstation import fence as gsfence
from groundstation import safety
from groundstation.safety import FenceConfig, Geofence

FENCE = FenceConfig.from_toml(Path(__file__).resolve().parents[2] / "configs" / "fence.toml")
INSIDE = np.array([0.3, -1.2, 1.0])
MARGIN = np.array([2.9, 0.4, 1.0])
V = np.array([0.8, 0.5, 0.1])
FAR = np.array([6.0, 1.0, 3.0])
IMPL = {"compiled": (gsfence.check_position, safety.limit_velocity, gsfence.clamp_position),
        "reference": (ref.check_position, ref.limit_velocity, ref.clamp_position)}


@pytest.mark.parametrize("impl", ["compiled", "reference"])
@pytest.mark.parametrize("case", ["gate", "inside", "margin", "check", "clamp"])
def test_bench_fence(benchmark, monkeypatch, impl, case):
    check, limit, clamp = IMPL[impl]
    if case == "gate":
        monkeypatch.setattr(safety, "check_position", check)
        monkeypatch.setattr(safety, "limit_velocity", limit)
        gf = Geofence(FENCE)
        out = benchmark(gf.filter_velocity, "cf1", INSIDE, V, 0.1)
        assert out.state is safety.GuardState.OK and not out.changed
    elif case in ("inside", "margin"):
        p = INSIDE if case == "inside" else MARGIN
        out = benchmark(lambda: limit(FENCE, p.copy(), V, 0.1))  # the reference clips p in place: a fresh copy
        np.testing.assert_array_equal(out, ref.limit_velocity(FENCE, p.copy(), V, 0.1))
    elif case == "check":
        assert benchmark(check, FENCE, MARGIN) is safety.FenceStatus.MARGIN
    else:
        out = benchmark(lambda: clamp(FENCE, FAR.copy()))
        np.testing.assert_array_equal(out, ref.clamp_position(FENCE, FAR.copy()))
    benchmark.extra_info["impl"] = impl
