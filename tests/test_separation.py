"""The separation filter (``groundstation.separation``): the motion model of its docstring simulated on a fine
time grid (one period of filtered commands, then braking at the acceleration limit), safe commands left
alone, bad input braked, the QP no worse than the fallback, and a closed loop of many periods."""
from __future__ import annotations

import math
import os
import signal

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from groundstation.separation import (STALE_PERIODS, JointFilter, Limits, QPSolver, SeparationConfig, Snapshot,
                                      default_min_distance, filter_velocities)
from runtime.spec import SpecError, SwarmSpec

LIM = Limits(min_distance=0.35, period=0.05, max_decel=2.0, max_speed=1.5, latency=0.1)
SIM_DT = 0.002


def _brake_path(p: np.ndarray, v: np.ndarray, a: float) -> list[np.ndarray]:
    """Positions [N, 2] on SIM_DT steps while every drone brakes in a straight line at ``a``."""
    out = []
    speed = np.linalg.norm(v, axis=1)
    u = np.divide(v, speed[:, None], out=np.zeros_like(v), where=speed[:, None] > 0)
    t_stop = speed / a
    for t in np.arange(SIM_DT, float(t_stop.max(initial=0.0)) + SIM_DT, SIM_DT):
        tt = np.minimum(t, t_stop)
        out.append(p + u * (speed * tt - 0.5 * a * tt * tt)[:, None])
    return out


def _trajectory(pos, vel, prev, cmd, lim: Limits, lag: bool) -> list[np.ndarray]:
    """The docstring's model: the latency flown on ``prev``, one period on ``cmd``, then braking. ``lag``:
    first-order tracking (time constant 0.2 s, the simulated Crazyflie's); else the velocity jumps."""
    p, v = pos.copy(), vel.copy()
    path = [p.copy()]
    for target, span in ((prev, lim.horizon - lim.period), (cmd, lim.period)):
        for _ in range(int(round(span / SIM_DT))):
            v = v + (target - v) * (SIM_DT / 0.2) if lag else target
            p = p + v * SIM_DT
            path.append(p.copy())
    return path + _brake_path(p, v, lim.max_decel)


def _min_pair_distances(path: list[np.ndarray]) -> np.ndarray:
    arr = np.stack(path)  # [T, N, 2]
    d = np.linalg.norm(arr[:, :, None, :] - arr[:, None, :, :], axis=-1)
    return d.min(0)


def _model_bound(pos, vel, prev, cmd, lim: Limits, extra: float = 0.0) -> np.ndarray:
    """[N, N] worst closing-in (sum over both drones) of the docstring's bound, written out independently;
    ``extra`` [s] lengthens the horizon (the recursive margin the filter keeps)."""
    s = np.maximum.reduce([np.full(len(pos), lim.max_speed / math.cos(math.pi / 8)), np.linalg.norm(vel, axis=1),
                           np.linalg.norm(prev, axis=1), np.linalg.norm(cmd, axis=1)])
    h = lim.horizon + extra + s / (2 * lim.max_decel)
    n = len(pos)
    out = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            e = (pos[i] - pos[j]) / np.linalg.norm(pos[i] - pos[j])
            close_i = max(0.0, -e @ vel[i], -e @ prev[i], -e @ cmd[i])
            close_j = max(0.0, e @ vel[j], e @ prev[j], e @ cmd[j])
            out[i, j] = h[i] * close_i + h[j] * close_j
    return out


@st.composite
def states(draw, moving: bool):
    n = draw(st.integers(2, 6))
    coords = st.floats(-1.5, 1.5, allow_nan=False)
    pos = np.array([[draw(coords), draw(coords)] for _ in range(n)])
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(n) * 9
    assume(d.min() >= LIM.min_distance)
    speeds = st.floats(-1.2, 1.2, allow_nan=False)
    vel = np.array([[draw(speeds), draw(speeds)] for _ in range(n)]) * (1.0 if moving else 0.0)
    prev = np.array([[draw(speeds), draw(speeds)] for _ in range(n)]) * (1.0 if moving else 0.0)
    want = np.array([[draw(speeds), draw(speeds)] for _ in range(n)]) * draw(st.sampled_from([0.5, 1.0, 3.0]))
    ctrl = np.array([draw(st.booleans()) for _ in range(n)])
    assume(ctrl.any())
    prev[~ctrl] = vel[~ctrl]  # an obstacle's command is what it does
    return pos, vel, prev, want, ctrl


def _check_separated(pos, vel, prev, res, ctrl, lim, only_feasible: bool) -> None:
    cmd = np.where(ctrl[:, None], res.velocity, vel)
    floor = _model_bound(pos, vel, prev, np.where(ctrl[:, None], 0 * cmd, vel), lim)  # momentum alone
    gap = np.linalg.norm(pos[:, None] - pos[None], axis=-1) - lim.min_distance
    feasible = floor <= gap + 1e-12
    for lag in (False, True):
        dmin = _min_pair_distances(_trajectory(pos, vel, prev, cmd, lim, lag))
        ok = dmin >= lim.min_distance - 1e-5  # VERIFY_TOL, and the time grid
        if only_feasible:
            ok |= ~(feasible & feasible.T)
        np.fill_diagonal(ok, True)
        assert ok.all(), f"pairs {np.argwhere(~ok).tolist()} closer than min_distance ({dmin.min():.4f} m)"


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(states(moving=False))
def test_from_rest_one_period_then_braking_keeps_every_pair_apart(state):
    pos, vel, prev, want, ctrl = state
    res = filter_velocities(pos, vel, want, ctrl, LIM, prev)
    assert not res.braked.any()  # from rest nothing is hopeless
    _check_separated(pos, vel, prev, res, ctrl, LIM, only_feasible=False)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(states(moving=True))
def test_with_momentum_every_pair_that_can_stay_apart_does(state):
    pos, vel, prev, want, ctrl = state
    res = filter_velocities(pos, vel, want, ctrl, LIM, prev)
    assert np.all(np.isfinite(res.velocity)) and np.all(res.velocity[~ctrl] == 0)
    assert np.all(res.velocity[res.braked] == 0)
    _check_separated(pos, vel, prev, res, ctrl, LIM, only_feasible=True)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(states(moving=True))
def test_commands_that_are_already_safe_pass_unchanged(state):
    pos, vel, prev, want, ctrl = state
    assume(np.linalg.norm(want, axis=1).max() <= LIM.max_speed)  # faster ones are cut to max_speed
    bound = _model_bound(pos, vel, prev, np.where(ctrl[:, None], want, vel), LIM, extra=LIM.horizon - LIM.period)
    gap = np.linalg.norm(pos[:, None] - pos[None], axis=-1) - LIM.min_distance
    np.fill_diagonal(gap, np.inf)
    assume(np.all(bound <= gap - 1e-6))
    res = filter_velocities(pos, vel, want, ctrl, LIM, prev)
    assert res.method == "unchanged"
    np.testing.assert_allclose(res.velocity[ctrl], want[ctrl], atol=1e-12)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(states(moving=False))
def test_the_qp_changes_commands_no_more_than_the_fallback(state):
    pos, vel, prev, want, ctrl = state
    qp = filter_velocities(pos, vel, want, ctrl, LIM, prev)
    fb = filter_velocities(pos, vel, want, ctrl, LIM, prev, use_qp=False)
    assert fb.method in ("unchanged", "pairwise")
    _check_separated(pos, vel, prev, fb, ctrl, LIM, only_feasible=False)
    # both minimise the change of the commands as the filter takes them, first cut to max_speed (the module
    # docstring); measured from the uncut wish the QP can look costlier (the test below)
    speed = np.linalg.norm(want, axis=1, keepdims=True)
    cut = want * np.minimum(1.0, LIM.max_speed / np.maximum(speed, 1e-12))
    cost = lambda r: float(((r.velocity - cut)[ctrl] ** 2).sum())  # noqa: E731
    assert cost(qp) <= cost(fb) + 1e-4  # the QP keeps QP_MARGIN back from its constraints


def test_the_qp_is_measured_against_the_wish_cut_to_max_speed():
    """The state a property search found (2026-12-03): from the uncut wish (3, 3) the QP looked 0.4 % costlier than
    the fallback (7.610 against 7.581); from the wish cut to 1.5 m/s, which both were asked for, it costs 0.001
    against 0.059."""
    pos = np.array([[0.0, 0.0], [-1.0, 1.0], [-1.0, -1.0]])
    want = np.array([[0.0, 0.0], [0.0, -1.5], [3.0, 3.0]])
    ctrl = np.array([False, True, True])
    qp = filter_velocities(pos, np.zeros((3, 2)), want, ctrl, LIM, np.zeros((3, 2)))
    fb = filter_velocities(pos, np.zeros((3, 2)), want, ctrl, LIM, np.zeros((3, 2)), use_qp=False)
    assert (qp.method, fb.method) == ("qp", "pairwise")
    cut = want.copy()
    cut[2] = [1.5 / math.sqrt(2)] * 2
    cost = lambda r: float(((r.velocity - cut)[ctrl] ** 2).sum())  # noqa: E731
    assert cost(qp) < 0.1 * cost(fb)
    assert np.linalg.norm(qp.velocity, axis=1).max() <= LIM.max_speed + 1e-6


def test_head_on_pair_shares_the_gap():
    pos = np.array([[0.0, 0.0], [1.0, 0.0]])
    res = filter_velocities(pos, np.zeros((2, 2)), np.array([[1.0, 0.0], [-1.0, 0.0]]), np.ones(2, bool), LIM)
    assert res.method == "qp"
    # each closes in by at most half of the 0.65 m gap over 0.1 s latency + 0.05 s period + 1.5 / (2 * 2) s of
    # braking + 0.1 s more latency (the recursive margin)
    # braking from the octagon's radius max_speed / cos(pi / 8)
    h = 0.1 + 0.05 + LIM.max_speed / math.cos(math.pi / 8) / (2 * 2.0) + 0.1
    np.testing.assert_allclose(res.velocity, [[0.325 / h, 0.0], [-0.325 / h, 0.0]], atol=1e-5)


def test_nan_coincident_and_obstacles():
    ones = np.ones(3, bool)
    pos = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]])
    want = np.array([[0.5, 0.0], [0.0, 0.5], [0.5, 0.5]])
    bad = pos.copy()
    bad[2, 0] = np.nan
    res = filter_velocities(bad, np.zeros((3, 2)), want, ones, LIM)
    assert res.method == "brake" and res.braked.all() and np.all(res.velocity == 0)
    nan_cmd = want.copy()
    nan_cmd[1] = np.nan
    res = filter_velocities(pos, np.zeros((3, 2)), nan_cmd, ones, LIM)
    assert res.braked.tolist() == [False, True, False] and np.all(res.velocity[1] == 0)
    np.testing.assert_allclose(res.velocity[[0, 2]], want[[0, 2]])
    same = np.array([[0.0, 0.0], [0.0, 0.0], [2.0, 2.0]])
    res = filter_velocities(same, np.zeros((3, 2)), want, ones, LIM)
    assert res.braked.tolist() == [True, True, False] and np.all(res.velocity[:2] == 0)
    # an obstacle rushing at a controlled drone that is in reach: the drone can do no more than brake
    pos2 = np.array([[0.0, 0.0], [0.5, 0.0]])
    res = filter_velocities(pos2, np.array([[0.0, 0.0], [-1.5, 0.0]]), np.array([[0.3, 0.0], [0.0, 0.0]]),
                            np.array([True, False]), LIM)
    assert res.braked.tolist() == [True, False] and np.all(res.velocity == 0)


def test_already_too_close_may_only_move_apart():
    pos = np.array([[0.0, 0.0], [0.3, 0.0]])
    res = filter_velocities(pos, np.zeros((2, 2)), np.array([[0.5, 0.4], [0.5, 0.0]]), np.ones(2, bool), LIM)
    assert res.velocity[0, 0] <= 1e-9 and res.velocity[1, 0] >= 0.5 - 1e-6
    assert abs(res.velocity[0, 1] - 0.4) < 1e-4  # sideways is free


def test_closed_loop_many_periods_never_closer_than_min_distance():
    """Eight drones in a small box, the desired commands drawn at random every period (half of them aimed at
    another drone), first-order tracking with the acceleration limit, positions measured every period."""
    rng = np.random.default_rng(3)
    n, lim = 8, LIM
    pos = np.array([[x, y] for x in (-0.9, -0.3, 0.3, 0.9) for y in (-0.4, 0.4)])
    vel = np.zeros((n, 2))
    prev = np.zeros((n, 2))
    dmin = np.inf
    braked = 0
    for step in range(400):
        want = rng.uniform(-1, 1, (n, 2))
        aim = rng.integers(0, n, n)
        chase = rng.random(n) < 0.5
        want[chase] = (pos[aim[chase]] - pos[chase]) * 3.0
        res = filter_velocities(pos, vel, want, np.ones(n, bool), lim, prev)
        braked += int(res.braked.sum())
        for _ in range(int(round(lim.period / 0.005))):
            acc = (res.velocity - vel) / 0.2
            norm = np.linalg.norm(acc, axis=1, keepdims=True)
            acc *= np.minimum(1.0, 5.0 / np.maximum(norm, 1e-9))
            vel = vel + acc * 0.005
            pos = np.clip(pos + vel * 0.005, -1.5, 1.5)  # walls: a drone stopped by one stays put
            d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(n) * 9
            dmin = min(dmin, float(d.min()))
        prev = res.velocity
    assert dmin >= lim.min_distance - 1e-3, dmin
    assert braked < 400 * n * 0.05


def test_joint_filter_solves_once_per_interval():
    state = {"calls": 0}

    def gather():
        state["calls"] += 1
        return Snapshot(["a", "b", "c"], np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]]), np.zeros((3, 2)),
                        np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 0.0]]), np.array([True, True, False]),
                        np.zeros((3, 2)))

    jf = JointFilter(LIM, gather, interval=0.05)
    a = jf.command("a", now=10.0)
    b = jf.command("b", now=10.01)
    assert state["calls"] == 1 and a[0] > 0 > b[0] and a[0] < 1.0
    assert np.all(jf.command("c", now=10.02) == 0)  # an obstacle is never commanded
    assert jf.stats()["solves"] == 2  # "c" was not in the cache
    jf.command("b", now=10.06)
    assert jf.stats()["solves"] == 2
    jf.command("b", now=10.08)
    assert jf.stats()["solves"] == 3 and state["calls"] == 3  # the interval passed


def test_started_filter_solves_on_its_own_thread():
    import threading

    from flight_fixtures import wait_until
    callers = []

    def gather():
        callers.append(threading.current_thread().name)
        return Snapshot(["a", "b"], np.array([[0.0, 0.0], [1.0, 0.0]]), np.zeros((2, 2)),
                        np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([True, True]), np.zeros((2, 2)))

    jf = JointFilter(LIM, gather, interval=0.01).start()
    try:
        assert wait_until(lambda: jf.stats()["solves"] >= 3, timeout=10.0)
        for _ in range(50):
            v = jf.command("a")
            assert v.tolist() == [0.0, 0.0] or 0 < v[0] < 1.0  # a brake only when this machine starved the solver
            assert jf.command("new").tolist() == [0.0, 0.0]  # not in the cache: brakes, no solve of its own
    finally:
        jf.stop()
    assert set(callers) == {"SeparationFilter"}  # a receive thread (here the test's) never solves
    assert jf.stats()["unplaced_setpoints"] == 50 and jf.stats()["solve_ms_p99"] > 0


def test_a_stalled_solver_thread_brakes_the_setpoints_and_never_holds_them_up():
    """The solver thread stuck in a solve (here: its snapshot blocks) must not stall the receive threads: once
    the cache is STALE_PERIODS intervals old they get a brake at once, and nobody solves in the solver's place
    (before, every receive thread solved in turn behind one lock: 50-300 ms stalls on a loaded machine)."""
    import threading
    import time

    from flight_fixtures import wait_until
    release, stuck = threading.Event(), threading.Event()
    calls = []

    def gather():
        calls.append(threading.current_thread().name)
        if len(calls) >= 2:  # the second solve hangs until the test releases it
            stuck.set()
            release.wait(30.0)
        return Snapshot(["a", "b"], np.array([[0.0, 0.0], [1.0, 0.0]]), np.zeros((2, 2)),
                        np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([True, True]), np.zeros((2, 2)))

    jf = JointFilter(LIM, gather, interval=0.01).start()
    try:
        assert stuck.wait(10.0)
        assert wait_until(lambda: time.monotonic() - jf._t >= STALE_PERIODS * jf.interval, timeout=10.0)
        t0 = time.monotonic()
        out = [jf.command(d) for d in ("a", "b") * 20]
        took = time.monotonic() - t0
        assert all(v.tolist() == [0.0, 0.0] for v in out)
        assert jf.stats()["stale_setpoints"] == 40 and jf.stats()["braked_setpoints"] >= 40
        assert not release.is_set() and took < 5.0  # answered while the solve was still stuck
        assert calls == ["SeparationFilter", "SeparationFilter"]
    finally:
        release.set()
        jf.stop()


def _closed_loop_states(n_steps: int, seed: int):
    """States of a closed loop like ``test_closed_loop_many_periods...``: 8 drones chasing each other, filtered."""
    rng = np.random.default_rng(seed)
    n = 8
    pos = np.array([[x, y] for x in (-0.9, -0.3, 0.3, 0.9) for y in (-0.4, 0.4)])
    vel, prev = np.zeros((n, 2)), np.zeros((n, 2))
    for _ in range(n_steps):
        want = rng.uniform(-1, 1, (n, 2))
        aim = rng.integers(0, n, n)
        chase = rng.random(n) < 0.5
        want[chase] = (pos[aim[chase]] - pos[chase]) * 3.0
        yield pos.copy(), vel.copy(), want, prev.copy()
        res = filter_velocities(pos, vel, want, np.ones(n, bool), LIM, prev)
        for _ in range(10):
            vel = vel + (res.velocity - vel) * (0.005 / 0.2)
            pos = np.clip(pos + vel * 0.005, -1.5, 1.5)
        prev = res.velocity


def test_warm_started_solves_equal_cold_ones():
    """A kept ``QPSolver`` (OSQP updated and warm-started while the constraint pattern holds) gives the cold
    solve's commands within the solver's tolerance, and each result passes the filter's own check."""
    solver = QPSolver()
    n_qp = 0
    for pos, vel, want, prev in _closed_loop_states(150, seed=5):
        ctrl = np.ones(len(pos), bool)
        cold = filter_velocities(pos, vel, want, ctrl, LIM, prev)
        warm = filter_velocities(pos, vel, want, ctrl, LIM, prev, solver=solver)
        assert warm.method == cold.method or {warm.method, cold.method} <= {"qp", "pairwise"}
        if warm.method == cold.method == "qp":
            n_qp += 1
            np.testing.assert_allclose(warm.velocity, cold.velocity, atol=2e-3)
        np.testing.assert_array_equal(warm.braked, cold.braked)
    assert n_qp >= 50 and solver.updates >= 10, (n_qp, solver.setups, solver.updates)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(states(moving=True))
def test_a_kept_solver_never_returns_a_setpoint_that_breaks_separation(state):
    """The same safety property as the cold solve's, with one ``QPSolver`` kept across every example (so that
    updates and warm starts from unrelated problems are exercised too)."""
    pos, vel, prev, want, ctrl = state
    res = filter_velocities(pos, vel, want, ctrl, LIM, prev, solver=_KEPT)
    assert np.all(np.isfinite(res.velocity)) and np.all(res.velocity[~ctrl] == 0)
    _check_separated(pos, vel, prev, res, ctrl, LIM, only_feasible=True)
    again = filter_velocities(pos, vel, want, ctrl, LIM, prev, solver=_KEPT)  # same pattern: an update
    _check_separated(pos, vel, prev, again, ctrl, LIM, only_feasible=True)


_KEPT = QPSolver()


def test_config():
    assert SeparationConfig().min_distance == pytest.approx(0.35)
    assert SeparationConfig().capture_distance == SwarmSpec().sensing.sensing_range
    big = SwarmSpec.from_dict({"pursuer": {"radius": 0.09, "max_speed": 1.0, "max_accel": 3.0}})
    assert default_min_distance(big) == pytest.approx(0.38)
    with pytest.raises(SpecError, match=r"separation\.min_dist: unknown key"):
        SeparationConfig.from_dict({"min_dist": 0.3})
    with pytest.raises(SpecError, match=r"separation\.min_distance: must be a finite number > 0"):
        SeparationConfig.from_dict({"min_distance": -0.3})
    with pytest.raises(SpecError, match=r"separation\.enabled: expected true or false"):
        SeparationConfig.from_dict({"enabled": 1})


def _snapshot(seed: int) -> Snapshot:
    pos, vel, want, prev = list(_closed_loop_states(seed + 3, seed=seed))[-1]
    return Snapshot([f"cf{k}" for k in range(len(pos))], pos, vel, want, np.ones(len(pos), bool), prev)


def test_the_solve_in_a_process_of_its_own_equals_the_threads_and_survives_losing_it():
    """``JointFilter(process=True)``: the commands come from the child (same as this thread's solve within the
    solver's tolerance); a killed child is replaced by this thread, and the setpoints go on."""
    from flight_fixtures import wait_until
    snap = _snapshot(7)
    ref = filter_velocities(snap.positions, snap.velocities, snap.desired, snap.controlled, LIM, snap.previous)
    assert ref.method == "qp"
    jf = JointFilter(LIM, lambda: snap, interval=0.02, process=True).start()
    try:
        assert jf.stats()["solver"] == "process"
        assert wait_until(lambda: jf.stats()["solves"] >= 3, timeout=30.0)
        got = np.array([jf.command(d) for d in snap.ids])
        np.testing.assert_allclose(got, ref.velocity, atol=2e-3)
        assert jf.stats()["qp_setups"] + jf.stats()["qp_updates"] >= 3  # counted in the child
        jf._worker._proc.kill()
        assert wait_until(lambda: jf.stats()["solver"] == "process, then thread", timeout=30.0)
        n = jf.stats()["solves"]
        assert wait_until(lambda: jf.stats()["solves"] >= n + 3, timeout=30.0)
        np.testing.assert_allclose(np.array([jf.command(d) for d in snap.ids]), ref.velocity, atol=2e-3)
    finally:
        jf.stop()
    assert jf._worker is None


def test_a_late_answer_from_the_solver_process_is_never_taken_for_a_newer_request():
    from groundstation.separation_worker import SolverProcess
    first, second = _snapshot(1), _snapshot(2)
    worker = SolverProcess(LIM).start()
    try:
        args = lambda s: (s.positions, s.velocities, s.desired, s.controlled, s.previous)  # noqa: E731
        # The child is held stopped while the first request is asked and not waited for, so its answer comes late
        # whatever the scheduler does (a parent preempted right after sending could otherwise find it answered).
        os.kill(worker._proc.pid, signal.SIGSTOP)
        try:
            assert worker.solve(*args(first), timeout=0.0) is None
        finally:
            os.kill(worker._proc.pid, signal.SIGCONT)
        velocity, braked, method = worker.solve(*args(second), timeout=30.0)
        ref = filter_velocities(*args(second)[:4], LIM, second.previous)
        assert method == ref.method
        np.testing.assert_allclose(velocity, ref.velocity, atol=2e-3)
        np.testing.assert_array_equal(braked, ref.braked)
    finally:
        worker.stop()
    assert not worker.alive
