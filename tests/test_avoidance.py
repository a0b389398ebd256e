"""The learned actors' avoidance layer (runtime.avoidance): what it leaves alone (a safe velocity within the max speed
and reachable from the own velocity), that it is the exact projection onto the safe, reachable velocities (against
a generic solver; onto the safe ones within the max speed when none is reachable), that it holds a wall-obstacle
wedge, that a team flown straight at its goals through it never touches an obstacle, a wall or a teammate in
the world (norm-limited acceleration included), that it is off by default without changing any spec's hash, and
that OnnxPolicy applies it.

``avoidance_cases`` (observations within the spec's ranges, with hazards placed near the drone) is shared with
tests/test_avoidance_c.py, which holds the C twin to the Python kernel on them."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from runtime.avoidance import (P_MATE_RADIUS, P_OWN_RADIUS, REACH_SHRINK, Avoidance, avoid_agents, avoid_rows,
                               role_tables)
from runtime.observation import encode_observations, new_knowledge, update_knowledge
from runtime.spec import Role, SwarmSpec
from runtime.world import World, action_to_velocity

ROOT = Path(__file__).resolve().parent.parent
ON = SwarmSpec.from_dict({"avoidance": {"enabled": True}})
PAIR = SwarmSpec.from_dict({"avoidance": {"enabled": True, "teammate_braking": 3.0}})
"""The shipped configs' layer: the teammate barrier planned at the pair's relative deceleration, 2 x braking."""


# --------------------------------------------------------------------------------------------------
# cases and an independent statement of the constraints


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.uniform(0.0, 2.0 * math.pi, n)
    return np.stack([np.cos(a), np.sin(a)], axis=-1)


def avoidance_cases(spec: SwarmSpec, role: Role, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` float32 observations of ``role`` within ``spec.layout(role).bounds()`` and actions in [-1, 1]^2.

    A quarter each: uniform; a wall within 0.3 m; an obstacle's surface within [-6 cm, 40 cm] of the body
    (slightly inside included); a valid teammate within [-3 cm, 50 cm] of touching. Around a third of the
    obstacle slots are empty (radius 0, half of them with junk offsets), a third of the teammate slots invalid
    (half zero as the encoder writes them, half junk), a few teammates coincide with the drone (d = 0) or carry
    a fractional valid flag. In the near cases the action points at the hazard half of the time. The own
    velocity: in 40% of the cases within 1.2 x the reachable radius of the action's velocity (mostly
    reachable), in 30% towards the near hazard at up to the max speed (closing in, sometimes faster than it can
    brake), else uniform within the bounds."""
    rng = np.random.default_rng(seed)
    lay = spec.layout(role)
    lo, hi = map(np.asarray, lay.bounds())
    obs = rng.uniform(lo, hi, (n, lay.dim))
    act = rng.uniform(-1.0, 1.0, (n, 2))
    params, _ = role_tables(spec, role)
    own_r, mate_r = params[P_OWN_RADIUS], params[P_MATE_RADIUS]
    rs = spec.role(role)
    hw = spec.arena.half_width
    sp = lay["self_pos"].start
    kind = rng.integers(0, 4, n)
    aim = rng.random(n) < 0.5
    hazard = _unit(rng, n)  # direction of the near hazard (uniform cases: any direction)

    ob = lay["obstacles"]
    obv = obs[:, ob.slice].reshape(n, ob.rows, 3)
    if ob.rows:
        empty = rng.random((n, ob.rows)) < 0.3
        obv[..., 2][empty] = 0.0
        obv[..., :2][empty & (rng.random((n, ob.rows)) < 0.5)] = 0.0
        near = kind == 2
        r = rng.uniform(spec.arena.obstacle_radius_min, spec.arena.obstacle_radius_max, n)
        u = _unit(rng, n)
        d = r + own_r + rng.uniform(-0.06, 0.4, n)
        obv[near, 0, :2] = (u * d[:, None])[near]
        obv[near, 0, 2] = r[near]
        act[near & aim] = (u * rng.uniform(0.3, 1.0, (n, 1)))[near & aim]
        hazard[near] = u[near]
    obs[:, ob.slice] = obv.reshape(n, -1)

    tm = lay["teammates"]
    tmv = obs[:, tm.slice].reshape(n, tm.rows, 5)
    if tm.rows:
        valid = rng.random((n, tm.rows)) < 0.67
        tmv[..., 4] = valid
        zero = ~valid & (rng.random((n, tm.rows)) < 0.5)
        tmv[zero] = 0.0
        odd = rng.random((n, tm.rows)) < 0.02
        tmv[..., 4][odd] = rng.uniform(0.3, 0.7, int(odd.sum()))
        near = kind == 3
        u = _unit(rng, n)
        d = own_r + mate_r + rng.uniform(-0.03, 0.5, n)
        tmv[near, 0, :2] = (u * d[:, None])[near]
        tmv[near, 0, 4] = 1.0
        same = near & (rng.random(n) < 0.02)
        tmv[same, 0, :2] = 0.0
        act[near & aim] = (u * rng.uniform(0.3, 1.0, (n, 1)))[near & aim]
        hazard[near] = u[near]
    obs[:, tm.slice] = tmv.reshape(n, -1)

    walls = kind == 1
    axis = rng.integers(0, 2, n)
    side = rng.choice([-1.0, 1.0], n)
    gap = rng.uniform(0.0, 0.3, n)
    rows = np.nonzero(walls)[0]
    obs[rows, sp + axis[rows]] = side[rows] * (hw - gap[rows])
    towards = np.zeros((n, 2))
    towards[np.arange(n), axis] = side * rng.uniform(0.3, 1.0, n)
    act[walls & aim] = towards[walls & aim]
    hazard[walls] = np.sign(towards[walls])

    sv = lay["self_vel"].slice
    vel_kind = rng.random(n)
    reach = rs.max_accel * spec.timing.control_period
    near_wish = act * rs.max_speed + _unit(rng, n) * rng.uniform(0.0, 1.2 * reach, (n, 1))
    closing = hazard * rng.uniform(0.0, rs.max_speed, (n, 1))
    obs[:, sv] = np.where((vel_kind < 0.4)[:, None], near_wish,
                          np.where((vel_kind < 0.7)[:, None], closing, obs[:, sv]))
    obs = np.clip(obs, lo, hi)
    return obs.astype(np.float32), act.astype(np.float32)


def _limit(g: float, braking: float, dt: float) -> float:
    return 0.0 if g <= 0.0 else min(math.sqrt(2.0 * braking * g), g / dt)


def constraints(spec: SwarmSpec, role: Role, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The layer's half-planes for one observation, from the spec's own fields (not the kernel's tables): unit
    normals pointing away from each hazard ``[m, 2]``, allowed approach speeds ``[m]`` and which ``[m]`` are
    obstacles or walls (True) rather than teammates. A velocity ``v`` is safe when ``n . v >= -limit``."""
    av, lay = spec.avoidance, spec.layout(role)
    own = spec.role(role).radius
    mates = [Role.EVADER] if role is Role.EVADER else [r for r in (Role.PURSUER, Role.SCOUT)
                                                       if len(spec.team.indices(r))]
    mate_r = max(spec.role(r).radius for r in mates)
    dt, b, hw = spec.timing.control_period, av.braking, spec.arena.half_width
    o = np.asarray(obs, dtype=np.float64)
    x, y = o[lay["self_pos"].slice]
    normals, limits, hard = [], [], []
    for dx, dy, vx, vy, valid in o[lay["teammates"].slice].reshape(-1, 5):
        d = math.hypot(dx, dy)
        if valid > 0.5 and d > 1e-9:
            normals.append((-dx / d, -dy / d))
            away = (vx * dx + vy * dy) / d  # the teammate's own speed away from this drone
            limits.append(0.5 * _limit(d - own - mate_r - av.teammate_margin, av.teammate_braking or b, dt)
                          + av.teammate_credit * max(away, 0.0))
            hard.append(False)
    for n, gap in (((-1, 0), hw - own - x), ((1, 0), hw - own + x), ((0, -1), hw - own - y), ((0, 1), hw - own + y)):
        normals.append(n)
        limits.append(_limit(gap - av.obstacle_margin, b, dt))
        hard.append(True)
    for dx, dy, r in o[lay["obstacles"].slice].reshape(-1, 3):
        d = math.hypot(dx, dy)
        if r > 0 and d > 1e-9:
            normals.append((-dx / d, -dy / d))
            limits.append(_limit(d - r - own - av.obstacle_margin, b, dt))
            hard.append(True)
    return np.array(normals, dtype=np.float64), np.array(limits), np.array(hard)


def violation(v: np.ndarray, normals: np.ndarray, limits: np.ndarray) -> float:
    """How far [m/s] the velocity ``v`` is beyond its worst half-plane (<= 0: within all of them)."""
    return float(np.max(-(normals @ v) - limits))


def discs(spec: SwarmSpec, role: Role, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The layer's two discs for one observation: centres ``[2, 2]`` and radii ``[2]`` of the speed limit (around
    zero) and of the velocities reachable in one control period (around the own velocity, radius max_accel x
    control period, less the kernel's documented ``REACH_SHRINK``)."""
    rs, lay = spec.role(role), spec.layout(role)
    own_vel = np.asarray(obs, dtype=np.float64)[lay["self_vel"].slice]
    reach = rs.max_accel * spec.timing.control_period * (1.0 - REACH_SHRINK)
    return np.array([[0.0, 0.0], own_vel]), np.array([rs.max_speed, reach])


def outside(v: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> float:
    """How far [m/s] the velocity ``v`` is outside its worst disc (<= 0: within all of them)."""
    return float(np.max(np.hypot(*(v[None] - centres).T) - radii))


def wish(spec: SwarmSpec, role: Role, act: np.ndarray) -> np.ndarray:
    """The actor's velocity as the world flies it (``runtime.world.action_to_velocity``, norm limited)."""
    return action_to_velocity(np.array([spec.role(role).max_speed]), np.asarray(act, np.float64)[None])[0]


def reference_projection(w: np.ndarray, normals: np.ndarray, limits: np.ndarray, centres: np.ndarray,
                         radii: np.ndarray, starts: list[np.ndarray]) -> np.ndarray | None:
    """The point nearest ``w`` with ``normals . v >= -limits`` and ``|v - centre_j| <= radius_j``, by a generic
    solver (scipy's SLSQP, the discs as smooth ``r^2 - |v - c|^2 >= 0``) from each of ``starts``: the nearest
    result that meets every constraint within 1e-9, or None if no start converged to one."""
    from scipy.optimize import minimize

    cons = [{"type": "ineq", "fun": lambda v: normals @ v + limits, "jac": lambda v: normals}]
    for c, r in zip(centres, radii):
        cons.append({"type": "ineq", "fun": lambda v, c=c, r=r: np.array([r * r - ((v - c) ** 2).sum()]),
                     "jac": lambda v, c=c: -2.0 * (v - c)[None]})
    best = None
    for x0 in starts:
        v = minimize(lambda v: ((v - w) ** 2).sum(), x0, jac=lambda v: 2.0 * (v - w), method="SLSQP",
                     constraints=cons, options={"ftol": 1e-16, "maxiter": 500}).x
        ok = violation(v, normals, limits) <= 1e-9 and outside(v, centres, radii) <= 1e-9
        if ok and (best is None or ((v - w) ** 2).sum() < ((best - w) ** 2).sum()):
            best = v
    return best


def _apply(spec: SwarmSpec, role: Role, obs: np.ndarray, act: np.ndarray) -> np.ndarray:
    out = np.array(act, copy=True)
    params, layout = role_tables(spec, role)
    avoid_rows(np.ascontiguousarray(obs), out, params, layout)
    return out


def _obs(spec: SwarmSpec, role: Role = Role.PURSUER, pos=(0.0, 0.0), vel=(0.0, 0.0)) -> np.ndarray:
    """A float64 observation with the own position and velocity set, empty obstacle and teammate slots."""
    lay = spec.layout(role)
    obs = np.zeros(lay.dim)
    obs[lay["self_pos"].slice] = pos
    obs[lay["self_vel"].slice] = vel
    return obs


ROLES = [Role.PURSUER, Role.SCOUT, Role.EVADER]


# --------------------------------------------------------------------------------------------------
# (a) safe, reachable velocities pass unchanged


@pytest.mark.parametrize("role", ROLES)
def test_a_safe_reachable_velocity_is_returned_unchanged(role):
    obs, act = avoidance_cases(ON, role, 4000, seed=1 + int(role))
    keep = np.zeros(len(obs), bool)
    for k, (o, a) in enumerate(zip(obs, act)):
        v = a.astype(np.float64) * ON.role(role).max_speed
        keep[k] = (violation(v, *constraints(ON, role, o)[:2]) < -1e-6 and outside(v, *discs(ON, role, o)) < -1e-6)
    assert keep.sum() > 500 and (~keep).sum() > 1500  # both kinds are exercised
    out = _apply(ON, role, obs, act)  # float32 actions, as every policy returns them
    np.testing.assert_array_equal(out[keep], act[keep])
    assert (out[~keep] != act[~keep]).any(axis=1).mean() > 0.9
    # float64 actions: the round trip through the velocity costs at most one rounding
    out64 = _apply(ON, role, obs.astype(np.float64), act.astype(np.float64))
    np.testing.assert_allclose(out64[keep], act[keep].astype(np.float64), rtol=5e-16, atol=0)


def test_an_open_arena_changes_nothing_while_the_drone_can_reach_the_command():
    lay = ON.layout(Role.PURSUER)
    act = np.array([[0.6, -0.7]], np.float32)
    obs = _obs(ON, vel=(0.5, -0.5)).astype(np.float32)[None]  # at the centre, 0.22 m/s from the command
    assert np.array_equal(_apply(ON, Role.PURSUER, obs, act), act)
    obs[0, lay["obstacles"].start:lay["obstacles"].start + 3] = (2.0, 0.0, 0.3)  # 1.6 m away
    assert np.array_equal(_apply(ON, Role.PURSUER, obs, act), act)
    # hovering, the drone gains at most max_accel x control period = 0.3 m/s: the command is cut to that
    a = act[0].astype(np.float64)
    out = _apply(ON, Role.PURSUER, _obs(ON)[None], a[None])[0]
    np.testing.assert_allclose(out, a / np.hypot(*a) * 0.3 * (1 - REACH_SHRINK), rtol=1e-12)


def test_actions_beyond_the_unit_disc_are_scaled_to_the_max_speed():
    obs = _obs(ON, vel=(0.6, 0.6))
    out = _apply(ON, Role.PURSUER, obs[None], np.array([[1.0, 1.0]]))
    np.testing.assert_allclose(out, [[math.sqrt(0.5), math.sqrt(0.5)]], rtol=1e-15)


# --------------------------------------------------------------------------------------------------
# (b) the exact projection: against a generic solver


@pytest.mark.parametrize("role", ROLES)
def test_the_layer_is_the_exact_projection_onto_safe_reachable_velocities(role):
    """Where a velocity that is safe, within the max speed and reachable exists (decided by the generic solver:
    the distance from the own velocity to the safe velocities within the max speed is below the reachable
    radius), the layer's velocity meets every half-plane and both discs within 1e-9 and equals the solver's
    optimum within 1e-6; where none exists, it meets every half-plane and the speed disc within 1e-9 and equals
    the solver's projection onto those. Float64 observations and actions, so the checks see the kernel's own
    rounding, not float32's."""
    obs, act = avoidance_cases(ON, role, 500, seed=2 + 10 * int(role))
    obs, act = obs.astype(np.float64), act.astype(np.float64)
    out = _apply(ON, role, obs, act) * ON.role(role).max_speed
    zero = np.zeros(2)
    n_reach = n_safe = 0
    active = np.zeros((3, 3), int)  # by the number of active half-planes and circles at the layer's velocity
    worst = 0.0
    for o, a, got in zip(obs, act, out):
        normals, limits, _ = constraints(ON, role, o)
        centres, radii = discs(ON, role, o)
        w, own = wish(ON, role, a), centres[1]
        nearest_to_own = reference_projection(own, normals, limits, centres[:1], radii[:1], [own, zero])
        assert nearest_to_own is not None
        slack = radii[1] - np.hypot(*(nearest_to_own - own))  # > 0: a safe, reachable velocity exists
        assert abs(slack) > 1e-7, "a case on the edge of feasibility: pick another seed"
        if slack > 0:
            n_reach += 1
            want = reference_projection(w, normals, limits, centres, radii,
                                        [w, zero, own, nearest_to_own, 0.5 * (w + nearest_to_own)])
            assert outside(got, centres, radii) <= 1e-9
        else:
            n_safe += 1
            want = reference_projection(w, normals, limits, centres[:1], radii[:1], [w, zero])
            assert outside(got, centres[:1], radii[:1]) <= 1e-9
        assert violation(got, normals, limits) <= 1e-9
        assert want is not None
        worst = max(worst, float(np.abs(got - want).max()))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
        lines = int((np.abs(normals @ got + limits) < 1e-9).sum())
        circles = int((np.abs(np.hypot(*(got - centres).T) - radii)[:1 + (slack > 0)] < 1e-9).sum())
        active[min(lines, 2), min(circles, 2)] += 1
    print(f"{role.label}: {n_reach} cases with a safe reachable velocity, {n_safe} without; active (lines, circles): "
          f"{ {(i, j): int(active[i, j]) for i in range(3) for j in range(3) if active[i, j]} }; max |layer - solver| "
          f"{worst:.2g} m/s")
    assert n_reach > 250 and n_safe > 50  # both branches exercised
    # every kind of candidate won somewhere: the wish, a line, a circle, line-circle, two lines, two circles
    assert active[0, 0] > 20 and active[1, 0] > 20 and active[0, 1] > 20 and active[1, 1] > 5
    assert active[2, 0] >= 1 and active[0, 2] >= 1


def _wedge(angle_deg: float, vel=(0.0, 0.0)) -> np.ndarray:
    """A pursuer 2.5 cm (inside the 4 cm margin) from the +y wall and from an obstacle's surface below it, the
    obstacle's centre at ``angle_deg`` from +x: a state the world allows (obstacles keep 0.2 m from the walls,
    less than a 0.15 m drone plus both margins)."""
    lay = ON.layout(Role.PURSUER)
    obs = _obs(ON, pos=(1.0, ON.arena.half_width - 0.075 - 0.025), vel=vel)
    r, a = 0.3, math.radians(angle_deg)
    o = lay["obstacles"].start
    obs[o:o + 3] = ((r + 0.075 + 0.025) * math.cos(a), (r + 0.075 + 0.025) * math.sin(a), r)
    return obs


@pytest.mark.parametrize("angle", [-60.0, -70.0, -80.0])
@pytest.mark.parametrize("vel", [(0.0, 0.0), (0.3, 0.0), (0.64, 0.0), (-0.2, -0.1)])
def test_the_layer_keeps_every_wall_and_obstacle_constraint_in_a_wedge(angle, vel):
    """Sliding along the +y wall (action (0.64, 0)) into the wedge between the wall and an obstacle, at rest or
    already moving: the layer commands no speed into the wall or the obstacle, both within their margins (a
    drone too fast to turn away within one period gets the safe command nearest its wish, reachable or not)."""
    obs = _wedge(angle, vel)
    out = _apply(ON, Role.PURSUER, obs[None], np.array([[0.64, 0.0]]))[0]
    normals, limits, hard = constraints(ON, Role.PURSUER, obs)
    assert (limits[hard] == 0).sum() == 2  # both inside their margins
    assert violation(out, normals, limits) <= 1e-9
    assert np.hypot(*out) <= 1.0 + 1e-12  # within the max speed


# --------------------------------------------------------------------------------------------------
# (c) one active constraint: the Euclidean projection


def _single(kind: str, rng: np.random.Generator, spec: SwarmSpec) -> tuple[np.ndarray, np.ndarray]:
    """A pursuer near the centre with exactly one hazard close (the walls 2 m away allow more than any speed)."""
    lay = spec.layout(Role.PURSUER)
    obs = _obs(spec, pos=rng.uniform(-0.8, 0.8, 2))
    u = _unit(rng, 1)[0]
    if kind == "obstacle":
        r = rng.uniform(0.25, 0.45)
        o = lay["obstacles"].start + 3 * int(rng.integers(lay["obstacles"].rows))
        obs[o:o + 2] = u * (r + 0.075 + rng.uniform(0.0, 0.3))
        obs[o + 2] = r
    elif kind == "teammate":
        o = lay["teammates"].start + 5 * int(rng.integers(lay["teammates"].rows))
        obs[o:o + 2] = u * (0.15 + rng.uniform(0.0, 0.3))
        obs[o + 2:o + 4] = rng.uniform(-1, 1, 2)
        obs[o + 4] = 1.0
    else:  # a wall: the drone 0 to 30 cm from the +x, -x, +y or -y wall, away from the others
        w = int(rng.integers(4))
        obs[lay["self_pos"].start + w // 2] = (1 if w % 2 == 0 else -1) * (3.0 - 0.075 - rng.uniform(0.0, 0.3))
    a = _unit(rng, 1)[0] * rng.uniform(0.2, 1.0)
    return obs, a


@pytest.mark.parametrize("kind", ["obstacle", "wall", "teammate"])
def test_a_single_active_constraint_is_the_exact_projection_onto_its_half_plane(kind):
    """The drone already flies the closed-form answer (the reachability disc is centred on it, and the speed
    disc contains it: a projection onto a half-plane holding 0 is never longer than the wish), so the only
    constraint that can bind is the hazard's: the layer returns the projection onto its half-plane."""
    from scipy.optimize import minimize

    rng = np.random.default_rng({"obstacle": 4, "wall": 5, "teammate": 6}[kind])
    lay = ON.layout(Role.PURSUER)
    active = 0
    for i in range(300):
        obs, a = _single(kind, rng, ON)
        n, lim, hard = constraints(ON, Role.PURSUER, obs)
        over = -(n @ a) - lim  # vmax = 1 for a pursuer
        assert (over > 0).sum() <= 1  # at most this one hazard is binding
        # the closed form: the point of {v : n . v >= -lim} nearest to a
        j = int(np.argmax(over))
        want = a + max(0.0, over[j]) * n[j]
        obs[lay["self_vel"].slice] = want
        got = _apply(ON, Role.PURSUER, obs[None], a[None])[0]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
        if over[j] > 0:
            active += 1
            assert abs(n[j] @ got + lim[j]) <= 1e-12  # on the boundary
            if i % 10 == 0:  # and what a generic solver finds for min |v - a|^2 subject to it
                res = minimize(lambda v: ((v - a) ** 2).sum(), a, jac=lambda v: 2 * (v - a), method="SLSQP",
                               constraints=[{"type": "ineq", "fun": lambda v: n[j] @ v + lim[j],
                                             "jac": lambda v: n[j]}], options={"ftol": 1e-15, "maxiter": 200})
                assert res.success
                np.testing.assert_allclose(got, res.x, atol=1e-7)
        else:
            np.testing.assert_array_equal(got, a)
    assert 30 < active < 290  # the hazard binds in a good share of the cases, not in all


def test_a_teammate_takes_half_the_budget_and_an_obstacle_all_of_it():
    """Head-on at the same gap, the drone already at the allowed speed: the approach speed left towards a
    teammate is half that towards an obstacle; with ``teammate_braking`` the half of the barrier planned at that
    deceleration."""
    lay = ON.layout(Role.PURSUER)
    gap = 0.3  # between the surfaces, before the margins
    b, dt = ON.avoidance.braking, ON.timing.control_period
    to_mate = 0.5 * _limit(gap - ON.avoidance.teammate_margin, b, dt)
    to_obstacle = _limit(gap - ON.avoidance.obstacle_margin, b, dt)
    mate = _obs(ON, vel=(to_mate, 0.0))
    t = lay["teammates"].start
    mate[t:t + 5] = (gap + 0.15, 0.0, 0.0, 0.0, 1.0)
    obst = _obs(ON, vel=(to_obstacle, 0.0))
    o = lay["obstacles"].start
    obst[o:o + 3] = (gap + 0.075 + 0.3, 0.0, 0.3)
    a = np.array([[1.0, 0.0]])
    assert _apply(ON, Role.PURSUER, mate[None], a)[0, 0] == pytest.approx(to_mate, abs=1e-12)
    assert _apply(ON, Role.PURSUER, obst[None], a)[0, 0] == pytest.approx(to_obstacle, abs=1e-12)
    # planned at the pair's relative deceleration (teammate_braking), each takes half of that barrier's limit
    b_pair = PAIR.avoidance.teammate_braking
    assert b_pair == 2 * b
    to_mate_pair = 0.5 * _limit(gap - PAIR.avoidance.teammate_margin, b_pair, dt)
    assert to_mate < to_mate_pair < to_obstacle
    mate_pair = mate.copy()
    mate_pair[lay["self_vel"].slice] = (to_mate_pair, 0.0)
    assert _apply(PAIR, Role.PURSUER, mate_pair[None], a)[0, 0] == pytest.approx(to_mate_pair, abs=1e-12)
    assert _apply(ON, Role.PURSUER, mate_pair[None], a)[0, 0] < to_mate_pair - 0.05
    # moving away is never limited, however close
    mate[t] = 0.1501
    mate[lay["self_vel"].slice] = (-1.0, 0.0)
    assert np.array_equal(_apply(ON, Role.PURSUER, mate[None], -a), -a)


def test_teammate_credit_lets_a_follower_keep_up_with_a_leader_flying_away_and_keeps_the_pair_within_the_limit():
    """``teammate_credit`` k: toward a teammate flying away at u the approach budget grows by k u, so a follower in
    a chase line is braked less, and the pair's closing speed (approach less the leader's retreat) stays within the
    half budget; a teammate that approaches earns no credit. Off (0), it serialises and hashes as before."""
    credit = SwarmSpec.from_dict({"avoidance": {"enabled": True, "teammate_credit": 0.5}})
    lay = ON.layout(Role.PURSUER)
    gap = 0.3
    half = 0.5 * _limit(gap - ON.avoidance.teammate_margin, ON.avoidance.braking, ON.timing.control_period)
    t = lay["teammates"].start
    a = np.array([[1.0, 0.0]])
    for leader_v in (0.8, 0.4, -0.3):  # flying away (+x, the direction of the teammate), slower, toward
        follower = _obs(ON, vel=(0.8, 0.0))
        follower[t:t + 5] = (gap + 0.15, 0.0, leader_v, 0.0, 1.0)
        plain = _apply(ON, Role.PURSUER, follower[None], a.copy())[0, 0] * ON.pursuer.max_speed
        got = _apply(credit, Role.PURSUER, follower[None], a.copy())[0, 0] * ON.pursuer.max_speed
        assert plain <= half + 1e-9  # the shipped layer: the leader's motion does not count
        if leader_v > 0:
            assert got > plain + 0.1 and got <= half + 0.5 * leader_v + 1e-9
            assert got - leader_v <= half + 1e-9  # the pair closes within the half budget
        else:
            assert got == pytest.approx(plain, abs=1e-12)  # no credit from a teammate that approaches
    assert "teammate_credit" not in ON.to_dict()["avoidance"]
    assert credit.hash != ON.hash and credit.to_dict()["avoidance"]["teammate_credit"] == 0.5
    assert SwarmSpec.from_dict(json.loads(json.dumps(credit.to_dict()))).hash == credit.hash


@pytest.mark.parametrize("role", ROLES)
def test_float32_observations_are_computed_in_float64(role):
    """OnnxPolicy and the C comparison pass float32 observations: the kernel computes with their float64 values,
    so the answer is the float64 observation's to the bit. (numba's ``float()`` keeps a float32 a float32: the
    normals were float32-rounded, the projection onto one missed its own line by ~1e-8, beyond FEASIBLE_TOL,
    and 11-13% of these rows got a feasible candidate up to 1.2 m/s farther from the wish than the optimum.)"""
    obs, act = avoidance_cases(ON, role, 6000, seed=20 + int(role))
    a32 = _apply(ON, role, obs, act.astype(np.float64))
    a64 = _apply(ON, role, obs.astype(np.float64), act.astype(np.float64))
    np.testing.assert_array_equal(a32, a64)


def test_non_finite_observations_leave_the_action_alone():
    obs, act = avoidance_cases(ON, Role.PURSUER, 8, seed=7)
    obs[::2, 5] = np.nan
    obs[1, 0] = np.inf
    out = _apply(ON, Role.PURSUER, obs, act)
    np.testing.assert_array_equal(out[::2], act[::2])
    np.testing.assert_array_equal(out[1], act[1])


# --------------------------------------------------------------------------------------------------
# (d) closed loop: a team flown straight at its goals through the layer


@pytest.mark.parametrize("spec_name, seed", [("ON", 11), ("ON", 21), ("ON", 31), ("PAIR", 11), ("PAIR", 21),
                                             ("PAIR", 31)])
def test_closed_loop_no_obstacle_wall_or_teammate_contacts_in_200_envs_over_100_steps(spec_name, seed):
    """Every agent of the default spec (layer on) is commanded at full speed straight at a goal: a random point
    of a square 30% wider than the arena (into the walls), an obstacle's centre, or a teammate's position; a
    new goal every 20 steps or when reached. The actions go through ``avoid_agents`` on the observations of
    ``encode_observations``; the world tracks them with its norm-limited acceleration. No agent may touch an
    obstacle or a wall, and no two pursuer-team agents, nor two evaders, may touch (pursuer-evader contacts are
    captures, which the layer does not prevent). With the default teammate barrier and with the shipped one
    (``PAIR``: each teammate brakes at ``braking``, not half of it)."""
    spec, n_envs, steps = {"ON": ON, "PAIR": PAIR}[spec_name], 200, 100
    world = World(spec, n_envs=n_envs, seed=seed)
    rng = np.random.default_rng(seed + 1)
    st = world.reset()
    knowledge = new_knowledge(spec, n_envs)
    n, nt, hw = spec.n_agents, spec.team.n_team, spec.arena.half_width
    goals = np.zeros((n_envs, n, 2))

    def new_goals(mask: np.ndarray) -> None:
        e, i = np.nonzero(mask)
        kind = rng.integers(0, 3, e.size)
        pts = rng.uniform(-1.3 * hw, 1.3 * hw, (e.size, 2))
        obst = st.obstacle_pos[e, rng.integers(0, spec.arena.n_obstacles, e.size)]
        mate = st.pos[e, rng.integers(0, nt, e.size)]
        goals[e, i] = np.where((kind == 0)[:, None], pts, np.where((kind == 1)[:, None], obst, mate))

    new_goals(np.ones((n_envs, n), bool))
    team = np.zeros((n, n), bool)
    team[:nt, :nt] = True
    team[nt:, nt:] = True
    radius = np.array(spec.per_agent("radius"))[None, :, None]
    obstacle_touch = mate_touch = wall_touch = changed = 0
    for t in range(steps):
        now = t * spec.timing.control_period
        update_knowledge(spec, knowledge, st.pos, st.vel, now)
        obs = encode_observations(spec, st.pos, st.vel, st.obstacle_pos, st.obstacle_radius, knowledge, now)
        to_goal = goals - st.pos
        dist = np.linalg.norm(to_goal, axis=-1, keepdims=True)
        act = to_goal / np.maximum(dist, 1e-9)
        raw = act.copy()
        avoid_agents(spec, obs, act)
        changed += int((np.abs(act - raw) > 1e-9).any(-1).sum())
        contacts = world.step(act)
        obstacle_touch += int(world.obstacle_contacts().sum())
        mate_touch += int((contacts & team[None]).sum() // 2)
        wall_touch += int((np.abs(st.pos) >= hw - radius - 1e-9).any(-1).sum())  # the world stops them there
        new_goals((dist[..., 0] < 0.1) | (t % 20 == 19))
    print(f"{spec_name} seed {seed}, {n_envs} envs x {steps} steps: {changed} agent-steps changed by the layer, {obstacle_touch} "
          f"obstacle contacts, {wall_touch} wall touches, {mate_touch} teammate contacts")
    assert changed > 0.1 * n_envs * steps * n  # the layer was at work, not idle
    assert (obstacle_touch, wall_touch, mate_touch) == (0, 0, 0)


# --------------------------------------------------------------------------------------------------
# (e) off by default: no-op, same hash, shipped models load


def test_off_the_layer_is_a_no_op_and_the_hash_is_unchanged():
    spec = SwarmSpec()
    assert not spec.avoidance.enabled
    obs, act = avoidance_cases(ON, Role.PURSUER, 64, seed=8)
    big = np.repeat(act[None], spec.n_agents, axis=0).transpose(1, 0, 2).copy()
    before = big.copy()
    o = np.zeros((64, spec.n_agents, spec.max_obs_dim), np.float32)
    o[:, :, :obs.shape[1]] = obs[:, None]
    assert avoid_agents(spec, o, big) is big
    np.testing.assert_array_equal(big, before)
    d = spec.to_dict()
    assert "avoidance" not in d
    assert SwarmSpec.from_dict(d).hash == spec.hash
    assert SwarmSpec.from_dict({**d, "avoidance": {"enabled": False}}).hash == spec.hash
    assert ON.hash != spec.hash and "avoidance" in ON.to_dict()
    assert SwarmSpec.from_dict(json.loads(json.dumps(ON.to_dict()))).hash == ON.hash
    # teammate_braking unset (0: braking) serialises and hashes as before the field existed; set, it counts
    assert "teammate_braking" not in ON.to_dict()["avoidance"]
    assert ON.avoidance.mate_braking == ON.avoidance.braking
    assert PAIR.hash != ON.hash and PAIR.to_dict()["avoidance"]["teammate_braking"] == 3.0
    assert SwarmSpec.from_dict(json.loads(json.dumps(PAIR.to_dict()))).hash == PAIR.hash
    # the layer on changes what a run with it does: the same state, its actions go through
    assert not np.array_equal(avoid_agents(ON, o, big.copy()), before)


def test_the_paper_setting_models_still_load_and_act_without_the_layer():
    from runtime.policy import load_models, read_manifest

    folder = ROOT / "models" / "paper_role_based"
    m = read_manifest(folder)
    doc = json.loads((folder / "manifest.json").read_text())
    assert "avoidance" not in doc["spec"] and m.spec.hash == doc["spec_hash"]
    _, pols = load_models(folder, agents=[0, len(m.agents) - 1])
    for pol in pols:
        assert pol.avoidance is None
        obs, _ = avoidance_cases(m.spec, pol.role, 4, seed=9)
        assert np.isfinite(pol.act_batch(obs)).all() and pol.faults == 0


# --------------------------------------------------------------------------------------------------
# (f) OnnxPolicy applies the layer to the network's output


@pytest.fixture(scope="module")
def on_models(tmp_path_factory) -> Path:
    pytest.importorskip("torch")
    from firmware_export.onnx_export import export_run
    from runtime_fixtures import make_run

    root = tmp_path_factory.mktemp("avoid_models")
    run = make_run(root / "run", ON, seed=3)
    export_run(run, root / "models", n_random=500, n_recorded=500)
    return root / "models"


@pytest.mark.parametrize("engine", ["onnxruntime", "compiled"])
def test_onnx_policy_returns_the_layer_applied_to_the_network_output(on_models, engine):
    from runtime.policy import load_models

    m, pols = load_models(on_models, engine=engine)
    _, raw_pols = load_models(on_models, engine=engine)
    assert m.spec.hash == ON.hash
    changed = 0
    for i in (0, ON.team.n_pursuers, ON.team.n_team):  # a pursuer, a scout, an evader
        pol, raw = pols[i], raw_pols[i]
        raw.avoidance = None  # the same network without the layer
        assert pol.avoidance is not None and pol.avoidance.role is pol.role
        obs, _ = avoidance_cases(ON, pol.role, 400, seed=10 + i)
        net = raw.act_batch(obs)
        want = Avoidance(ON, pol.role).apply(obs, net.copy())
        np.testing.assert_array_equal(pol.act_batch(obs), want)
        for k in range(0, 400, 7):  # one at a time, float32 and float64 observations
            np.testing.assert_array_equal(pol.act(obs[k]), want[k])
            np.testing.assert_array_equal(pol.act(obs[k].astype(np.float64)),
                                          _apply(ON, pol.role, obs[k:k + 1].astype(np.float64),
                                                 raw.act(obs[k])[None])[0])
        changed += int((want != net).any(axis=1).sum())
        assert pol.faults == 0
    assert changed > 0.1 * 3 * 400  # the layer changed a good share of the network's actions


def test_the_shipped_models_carry_the_layer_and_apply_it():
    from runtime.policy import load_models, read_manifest

    folder = ROOT / "models" / "role_based"
    m = read_manifest(folder)
    assert m.spec.avoidance.enabled and m.spec.hash == json.loads((folder / "manifest.json").read_text())["spec_hash"]
    _, pols = load_models(folder, agents=[0, len(m.agents) - 1])
    for pol in pols:
        assert pol.avoidance is not None
        obs, _ = avoidance_cases(m.spec, pol.role, 4, seed=9)
        assert np.isfinite(pol.act_batch(obs)).all() and pol.faults == 0
