"""The geofence: no setpoint leaves it, for any input."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fence_strategies import fences, point, sane_point
from groundstation.safety import (FenceConfig, FenceStatus, Geofence, GuardState, KeepOut, check_position,
                                  clamp_path, clamp_position, in_safe_set, limit_velocity)
from runtime.spec import SpecError, SwarmSpec

ROOT = Path(__file__).resolve().parents[1]
TOL = 1e-6
PROPS = settings(max_examples=200, deadline=None)


def _segment_safe(fence: FenceConfig, a: np.ndarray, b: np.ndarray, n: int = 12) -> bool:
    return all(in_safe_set(fence, a + (b - a) * t, TOL) for t in np.linspace(0.0, 1.0, n))


# -- config --------------------------------------------------------------------------------------------


def test_fence_toml_loads_and_has_a_safe_home() -> None:
    f = FenceConfig.from_toml(ROOT / "configs" / "fence.toml")
    assert len(f.keep_out) == 3 and f.margin == 0.2
    assert in_safe_set(f, f.home)
    np.testing.assert_allclose(f.safe_polygon.min(axis=0), [-2.8, -2.8])


@pytest.mark.parametrize("data, field", [
    ({"margni": 0.1}, "fence.margni"),
    ({"margin": -0.1}, "fence.margin"),
    ({"margin": 3.5, "z_max": 9.0}, "fence.margin"),
    ({"z_min": 1.0, "z_max": 1.2}, "fence.z_max"),
    ({"max_decel": 0.0}, "fence.max_decel"),
    ({"box": [1.0, -1.0, -1.0, 1.0]}, "fence.box"),
    ({"box": [1.0, 2.0]}, "fence.box"),
    ({"vertices": [[0, 0], [1, 0]]}, "fence.vertices"),
    ({"vertices": [[0, 0], [2, 0], [1, 0.2], [2, 2], [0, 2]]}, "fence.vertices"),   # concave
    ({"vertices": [[0, 0], [1, 0], [1]]}, "fence.vertices[2]"),
    ({"keep_out": [{"x": 0, "y": 0, "radius": -1}]}, "fence.keep_out[0].radius"),
    ({"keep_out": [{"x": 0, "y": 0}]}, "fence.keep_out[0].radius"),
    ({"keep_out": [{"x": 0, "y": 0, "radius": 5.0}]}, "fence.keep_out"),
    ({"hold_time": "long"}, "fence.hold_time"),
])
def test_bad_configs_name_the_field(data: dict, field: str) -> None:
    with pytest.raises(SpecError) as err:
        FenceConfig.from_dict(data)
    assert str(err.value).startswith(field), str(err.value)


def test_default_fence_from_the_spec_arena_with_obstacles() -> None:
    spec = SwarmSpec()
    f = FenceConfig.from_spec(spec, obstacles=np.array([[1.0, 1.0, 0.3]]), margin=0.1)
    hw = spec.arena.half_width
    np.testing.assert_allclose(f.polygon.min(axis=0), [-hw, -hw])
    assert f.keep_out == (KeepOut(1.0, 1.0, 0.3),) and f.margin == 0.1
    assert check_position(f, (1.0, 1.1, 1.0)) is FenceStatus.OUTSIDE


# -- pure functions ------------------------------------------------------------------------------------


def test_check_position_classes() -> None:
    f = FenceConfig(keep_out=(KeepOut(0.0, 0.0, 0.3),))
    assert check_position(f, (1.0, 1.0, 1.0)) is FenceStatus.INSIDE
    assert check_position(f, (2.9, 0.0, 1.0)) is FenceStatus.MARGIN
    assert check_position(f, (0.4, 0.0, 1.0)) is FenceStatus.MARGIN
    assert check_position(f, (0.2, 0.0, 1.0)) is FenceStatus.OUTSIDE
    assert check_position(f, (3.1, 0.0, 1.0)) is FenceStatus.OUTSIDE
    assert check_position(f, (1.0, 1.0, 2.1)) is FenceStatus.OUTSIDE
    assert check_position(f, (1.0, 1.0, 0.0)) is FenceStatus.LOW
    assert check_position(f, (math.nan, 1.0, 1.0)) is FenceStatus.OUTSIDE
    assert check_position(f, None) is FenceStatus.OUTSIDE


def test_clamp_is_the_nearest_safe_point_on_simple_cases() -> None:
    f = FenceConfig(keep_out=(KeepOut(0.0, 0.0, 0.3),))
    np.testing.assert_allclose(clamp_position(f, (5.0, 0.5, 9.0)), (2.8, 0.5, 1.8))
    np.testing.assert_allclose(clamp_position(f, (0.1, 0.0, 1.0)), (0.5, 0.0, 1.0), atol=1e-9)
    np.testing.assert_allclose(clamp_position(f, (1.0, 1.0, 1.0)), (1.0, 1.0, 1.0))


def test_non_finite_setpoints_fall_back() -> None:
    f = FenceConfig()
    np.testing.assert_allclose(clamp_position(f, (math.nan, 0, 1), fallback=(1.0, 2.0, 1.0)), (1.0, 2.0, 1.0))
    np.testing.assert_allclose(clamp_position(f, (math.inf, 0, 1), fallback=(9.0, 0.0, 1.0)), (2.8, 0.0, 1.0))
    np.testing.assert_allclose(clamp_position(f, None), f.home)
    np.testing.assert_array_equal(limit_velocity(f, (0, 0, 1), (math.nan, 1, 0), 0.1), np.zeros(3))
    np.testing.assert_array_equal(limit_velocity(f, (0, 0, 1), (1, 0, 0), math.nan), np.zeros(3))


def test_velocity_toward_a_wall_slows_to_the_stopping_distance() -> None:
    from groundstation.cf_firmware import WDT_SHUTDOWN_S

    f = FenceConfig(max_speed=1.5, max_decel=2.0)
    assert f.coast_time == WDT_SHUTDOWN_S == 2.0  # the Crazyflie's setpoint watchdog: motors off at 2 s
    far = limit_velocity(f, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), 0.1)
    np.testing.assert_allclose(far, (1.0, 0.0, 0.0))
    fast = limit_velocity(f, (0.0, 0.0, 1.0), (30.0, 0.0, 0.0), 0.1)
    np.testing.assert_allclose(fast, (2.8 / 2.0, 0.0, 0.0), atol=1e-5)  # 2.8 m free, coasting for 2 s
    near = limit_velocity(f, (2.6, 0.0, 1.0), (1.0, 0.0, 0.0), 0.1)   # 0.2 m to the safe edge
    s = near[0]
    assert 0 < s < 1.0 and s * 0.1 + s * s / (2 * 2.0) <= 0.2 + 1e-9 and s * 2.0 <= 0.2 + 1e-9
    assert s == pytest.approx(0.1, abs=1e-5)  # the coast is the longer path here
    braking_only = FenceConfig(max_speed=1.5, max_decel=2.0, coast_time=1e-6)
    sb = limit_velocity(braking_only, (2.6, 0.0, 1.0), (1.0, 0.0, 0.0), 0.1)[0]
    assert sb > 2 * s and sb * 0.1 + sb * sb / (2 * 2.0) == pytest.approx(0.2, abs=1e-5)
    away = limit_velocity(f, (2.8, 0.0, 1.0), (-1.0, 0.0, 0.0), 0.1)
    np.testing.assert_allclose(away, (-1.0, 0.0, 0.0))


@PROPS
@given(fence=fences(), p=point, fb=st.one_of(st.none(), point))
def test_clamped_positions_are_always_inside(fence: FenceConfig, p: tuple, fb: tuple | None) -> None:
    q = clamp_position(fence, p, fb)
    assert q.shape == (3,) and np.all(np.isfinite(q))
    assert in_safe_set(fence, q, TOL)
    assert check_position(fence, q) is FenceStatus.INSIDE or in_safe_set(fence, q, TOL)


@settings(max_examples=25, deadline=None)
@given(fence=fences(), p=sane_point)
def test_clamp_is_no_farther_than_any_safe_grid_point(fence: FenceConfig, p: tuple) -> None:
    q = clamp_position(fence, p)
    lo, hi = fence.safe_polygon.min(axis=0), fence.safe_polygon.max(axis=0)
    xs, ys = np.meshgrid(np.linspace(lo[0], hi[0], 41), np.linspace(lo[1], hi[1], 41))
    zlo, zhi = fence.z_band
    z = min(max(p[2], zlo), zhi)
    grid = [np.array([x, y, z]) for x, y in zip(xs.ravel(), ys.ravel()) if in_safe_set(fence, (x, y, z), 0.0)]
    cell = float(np.hypot(*(hi - lo))) / 40
    best = min(float(np.linalg.norm(g - np.asarray(p))) for g in grid)
    assert float(np.linalg.norm(q - np.asarray(p))) <= best + 1e-9
    # the grid only bounds the optimum from above within its resolution: the grid points nearest the optimum
    # can fall just outside a thin safe region, so allow two cells (one cell failed at 0.0577 > 0.0575)
    assert float(np.linalg.norm(q - np.asarray(p))) >= best - 2 * cell


@PROPS
@given(fence=fences(), start=sane_point, vs=st.lists(point, min_size=1, max_size=15),
       dt=st.floats(0.01, 0.5))
def test_limited_velocities_never_cross_the_fence(fence: FenceConfig, start: tuple, vs: list, dt: float) -> None:
    """Integrate the limited velocities of an adversarial sequence, braking at max_decel after each; the
    path never leaves the safe set."""
    p = clamp_position(fence, start)
    for v in vs:
        w = limit_velocity(fence, p, v, dt)
        assert np.all(np.isfinite(w)) and np.linalg.norm(w) <= fence.max_speed + 1e-9
        nxt = p + w * dt
        assert _segment_safe(fence, p, nxt)
        speed = float(np.linalg.norm(w))
        if speed > 0:
            stop = nxt + w / speed * speed ** 2 / (2 * fence.max_decel)
            assert _segment_safe(fence, nxt, stop)
        p = nxt


@PROPS
@given(fence=fences(), start=sane_point, vs=st.lists(point, min_size=1, max_size=15),
       dt=st.floats(0.01, 0.5), silent_after=st.integers(0, 14), drag=st.floats(0.0, 1.0))
def test_a_drone_coasting_after_its_last_setpoint_stays_inside(fence: FenceConfig, start: tuple, vs: list,
                                                                dt: float, silent_after: int, drag: float) -> None:
    """The ground station falls silent after any setpoint: the Crazyflie flies it for 0.5 s, then levels
    out with x and y control off and coasts (slowed only by drag, its height in velocity mode going on) until
    the motors stop at ``coast_time``. The whole coast stays in the safe set."""
    p = clamp_position(fence, start)
    for k, v in enumerate(vs):
        w = limit_velocity(fence, p, v, dt)
        if k == silent_after or k == len(vs) - 1:
            t, step, q, vel = 0.0, fence.coast_time / 50, p.copy(), w.copy()
            while t < fence.coast_time - 1e-12:
                if t >= 0.5:
                    vel[:2] *= math.exp(-drag * step)
                q = q + vel * step
                t += step
                assert in_safe_set(fence, q, TOL)
            return
        p = p + w * dt


@settings(max_examples=100, deadline=None)
@given(fence=fences(), start=sane_point, vs=st.lists(point, min_size=1, max_size=8), dt=st.floats(0.01, 0.5))
def test_from_outside_the_safe_set_velocities_only_lead_back(fence: FenceConfig, start: tuple, vs: list,
                                                               dt: float) -> None:
    p = np.asarray(start, dtype=float)
    for v in vs:
        d0 = float(np.linalg.norm(clamp_position(fence, p) - p))
        p = p + limit_velocity(fence, p, v, dt) * dt
        assert float(np.linalg.norm(clamp_position(fence, p) - p)) <= d0 + 1e-9


@PROPS
@given(fence=fences(), start=sane_point, target=point)
def test_position_paths_stay_inside(fence: FenceConfig, start: tuple, target: tuple) -> None:
    s = clamp_position(fence, start)
    q = clamp_path(fence, s, target)
    assert in_safe_set(fence, q, TOL)
    assert _segment_safe(fence, s, q)


# -- the guard -----------------------------------------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_outside_holds_then_lands_and_counts() -> None:
    clock = FakeClock()
    gf = Geofence(FenceConfig(hold_time=1.0), clock=clock)
    out = gf.filter_velocity("d1", (0.0, 0.0, 1.0), (0.5, 0.0, 0.0), 0.1)
    assert out.state is GuardState.OK and not out.changed
    out = gf.filter_velocity("d1", (3.3, 0.0, 1.0), (0.5, 0.0, 0.0), 0.1)
    assert out.state is GuardState.HOLD and np.all(out.value == 0)
    clock.t += 0.5
    assert gf.filter_velocity("d1", (0.0, 0.0, 1.0), (0.5, 0.0, 0.0), 0.1).state is GuardState.OK  # back in
    gf.filter_velocity("d1", (3.3, 0.0, 1.0), (0.5, 0.0, 0.0), 0.1)
    clock.t += 0.9
    assert gf.filter_position("d1", (3.3, 0.0, 1.0), (9.0, 0.0, 1.0)).state is GuardState.HOLD
    clock.t += 0.2
    out = gf.filter_position("d1", (3.3, 0.0, 1.0), (9.0, 0.0, 1.0))
    assert out.state is GuardState.LAND and in_safe_set(gf.fence, out.value)
    clock.t += 5
    assert gf.filter_velocity("d1", (0.0, 0.0, 1.0), (0.5, 0.0, 0.0), 0.1).state is GuardState.LAND  # latched
    st_ = gf.stats("d1")
    assert st_.violations == 2 and st_.landings == 1 and st_.setpoints == 7
    gf.reset("d1")
    assert gf.filter_velocity("d1", (0.0, 0.0, 1.0), (0.5, 0.0, 0.0), 0.1).state is GuardState.OK
    assert gf.stats("d2").setpoints == 0


def test_unknown_position_is_treated_as_outside() -> None:
    clock = FakeClock()
    gf = Geofence(FenceConfig(hold_time=0.5), clock=clock)
    assert gf.filter_velocity("d", None, (1, 0, 0), 0.1).state is GuardState.HOLD
    clock.t += 0.6
    assert gf.filter_velocity("d", (math.nan, 0, 1), (1, 0, 0), 0.1).state is GuardState.LAND
    assert gf.stats("d").non_finite == 2


@settings(max_examples=100, deadline=None)
@given(seq=st.lists(st.tuples(point, point, st.sampled_from(["v", "p"])), min_size=1, max_size=20),
       fence=fences())
def test_geofence_output_always_inside(seq: list, fence: FenceConfig) -> None:
    clock = FakeClock()
    gf = Geofence(fence, clock=clock)
    for measured, sp, kind in seq:
        clock.t += 0.1
        if kind == "p":
            out = gf.filter_position("d", measured, sp)
            assert in_safe_set(fence, out.value, TOL)
        else:
            out = gf.filter_velocity("d", measured, sp, 0.1)
            assert np.linalg.norm(out.value) <= fence.max_speed + 1e-9
            m = np.asarray(measured, dtype=float)
            if in_safe_set(fence, m):
                assert _segment_safe(fence, m, m + out.value * 0.1)


def test_takeoff_height_is_clamped_into_the_band() -> None:
    gf = Geofence(FenceConfig())
    assert gf.clamp_height(5.0) == pytest.approx(1.8)
    assert gf.clamp_height(math.nan) == pytest.approx(0.4)
    assert gf.clamp_height(1.0) == 1.0


def test_one_drones_geometry_never_holds_up_another_drones_setpoint(monkeypatch) -> None:
    """Every link's receive thread passes the one Geofence: the geometry runs outside its lock (with it inside,
    the 12 receive threads of the demo queued behind each other: p99 59-65 ms in the ground station)."""
    import threading

    from groundstation import safety
    entered, release = threading.Event(), threading.Event()
    real = safety.limit_velocity

    def slow_for_a(fence, p, v, dt):
        if threading.current_thread().name == "a":
            entered.set()
            release.wait(30.0)
        return real(fence, p, v, dt)

    monkeypatch.setattr(safety, "limit_velocity", slow_for_a)
    gf = Geofence(FenceConfig())
    t = threading.Thread(target=gf.filter_velocity, args=("cf_a", (0, 0, 1), (0.5, 0, 0), 0.1), name="a")
    t.start()
    try:
        assert entered.wait(10.0)
        out = gf.filter_velocity("cf_b", (0, 0, 1), (0.3, 0, 0), 0.1)  # would block here with the lock held
        assert out.state is GuardState.OK and out.value[0] == pytest.approx(0.3)
        assert not release.is_set()
    finally:
        release.set()
        t.join(10.0)
    assert gf.stats("cf_a").setpoints == gf.stats("cf_b").setpoints == 1


def test_concurrent_setpoints_are_counted_and_filtered_as_serial_ones() -> None:
    import threading

    fence = FenceConfig()
    rng = np.random.default_rng(0)
    work = {f"cf{k}": [(rng.uniform(-2.5, 2.5, 3) * (1, 1, 0.4) + (0, 0, 1), rng.uniform(-3, 3, 3))
                       for _ in range(300)] for k in range(8)}
    serial, shared = Geofence(fence, clock=lambda: 0.0), Geofence(fence, clock=lambda: 0.0)  # timing-free
    want = {d: [serial.filter_velocity(d, p, v, 0.1) for p, v in seq] for d, seq in work.items()}
    got: dict[str, list] = {}
    threads = [threading.Thread(target=lambda d=d, seq=seq: got.__setitem__(
        d, [shared.filter_velocity(d, p, v, 0.1) for p, v in seq])) for d, seq in work.items()]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60.0)
    for d in work:
        assert [(o.state, o.changed) for o in got[d]] == [(o.state, o.changed) for o in want[d]]
        np.testing.assert_array_equal(np.array([o.value for o in got[d]]), np.array([o.value for o in want[d]]))
        assert shared.stats(d) == serial.stats(d)
