"""The learned actors' avoidance layer: a velocity barrier computed from one drone's own observation.

Every trained actor of a spec with ``spec.avoidance.enabled`` acts through it: the trainer between the actors
and the world, the evaluator, ``runtime.policy.OnnxPolicy`` (so the per-drone runtime and the ground station's
demo) and the C app on the drone (``swarm_avoid`` in its ``swarm_logic.c``, with the numbers below generated into
``policy.h`` by ``firmware_export.cgen_avoid``). The actor proposes a velocity ``w``; the layer commands the
velocity nearest to it (Euclidean) among those that are

- safe: toward every obstacle and wall the speed is at most ``limit(gap, obstacle_margin, braking)``, toward every
  teammate in the observation at most ``limit(gap, teammate_margin, mate_braking) / 2`` (the teammate, flying the
  same layer, takes the other half), with ``limit(g, m, b) = min(sqrt(2 b (g - m)), (g - m) / control_period)``
  for ``g > m``, else 0: a drone that keeps to it can stop before the margin at ``braking`` (< its ``max_accel``)
  and never covers the remaining gap within one control period. Toward a teammate each of the two keeps its own
  approach speed within ``sqrt(2 b g) / 2``, which shrinks as the pair closes in at up to twice that: following
  it asks of each a deceleration of ``b / 2``, so ``mate_braking`` (``spec.avoidance.teammate_braking``, default
  ``braking``) at ``2 x braking`` asks of each teammate what an obstacle asks. With ``teammate_credit`` k, a
  teammate's own speed away from the drone (``u > 0``, from its velocity in the observation) adds ``k u`` to that
  half: the pair's closing speed at those velocities stays within ``limit`` for ``k <= 1`` (the drone's approach
  less the teammate's retreat is at most its half; a teammate that approaches earns no credit), and a follower in
  a chase line is not braked by a leader flying away. Each is a half-plane ``c . n >= -limit``;
- within the role's ``max_speed`` (a disc around zero);
- reachable in one control period: within ``max_accel x control_period`` of the drone's own velocity (a disc),
  because the drone tracks its command with a norm-limited acceleration (``runtime.world``): a command it can
  reach is the velocity it flies, so the limits hold for the velocity, not only for the command. Without this,
  a drone that turns as it nears an obstacle spends its acceleration on the turn and enters the margin still
  closing in.

That is a two-variable quadratic program with half-planes and two discs; its optimum has at most two active
constraints, so the layer solves it exactly by trying every candidate (the wish itself, its projection onto
each boundary, every intersection of two boundaries) and keeping the nearest feasible one. If no velocity is
both safe and reachable (the drone is closing in faster than it can brake this period), the reachability disc
is dropped: the safe velocity nearest the wish is commanded, and the drone brakes toward it as hard as it can.
Zero velocity is always safe, so the program always has a solution. A velocity that is already safe and
reachable is returned unchanged.

Inputs are what the drone's observation holds (``spec.layout(role)``): its own position and velocity, the
obstacles (centre offset and radius; empty slots have radius 0), the teammates (offset, velocity, valid flag);
walls come from the own position and ``spec.arena``. Evaders keep away from the other evaders and from obstacles
and walls; touching a pursuer is a capture, not a collision, so threats are not constrained.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from runtime.spec import Role, SwarmSpec

# params: float64 [11]
(P_OWN_RADIUS, P_MATE_RADIUS, P_MAX_SPEED, P_MAX_ACCEL, P_HALF_WIDTH, P_DT, P_BRAKING, P_OBS_MARGIN,
 P_MATE_MARGIN, P_MATE_BRAKING, P_MATE_CREDIT) = range(11)
# layout: int64 [6]
L_SELF_POS, L_SELF_VEL, L_OBSTACLES, L_N_OBSTACLES, L_MATES, L_N_MATES = range(6)
MATE_COLUMNS = 5
"""dx, dy, vx, vy, valid: the teammates field of every layout."""
FEASIBLE_TOL = 1e-9
"""Slack [m/s] of the feasibility test of a candidate (float64 rounding of the intersections)."""
REACH_SHRINK = 1e-6
"""The reachability disc's radius is ``max_accel x control_period x (1 - REACH_SHRINK)``, so that rounding in the
world's own limit never clips a command the layer chose."""


def role_tables(spec: SwarmSpec, role: Role) -> tuple[np.ndarray, np.ndarray]:
    """The kernel's ``params`` and ``layout`` arrays for actors of ``role``."""
    role = Role(role)
    av = spec.avoidance
    lay = spec.layout(role)
    if role is Role.EVADER:
        mates = [Role.EVADER]
    else:
        mates = [r for r in (Role.PURSUER, Role.SCOUT) if len(spec.team.indices(r))]
    mate_radius = max(spec.role(r).radius for r in mates)  # slots do not say who is who: the largest
    rs = spec.role(role)
    params = np.array([rs.radius, mate_radius, rs.max_speed, rs.max_accel, spec.arena.half_width,
                       spec.timing.control_period, av.braking, av.obstacle_margin, av.teammate_margin,
                       av.mate_braking, av.teammate_credit],
                      dtype=np.float64)
    ob, tm = lay["obstacles"], lay["teammates"]
    assert len(tm.columns) == MATE_COLUMNS and tm.columns[-1] == "valid", tm.columns
    layout = np.array([lay["self_pos"].start, lay["self_vel"].start, ob.start, ob.rows, tm.start, tm.rows],
                      dtype=np.int64)
    return params, layout


@njit(cache=True, nogil=True)
def _limit(gap, margin, braking, dt):
    g = gap - margin
    if not g > 0.0:
        return 0.0
    return min(math.sqrt(2.0 * braking * g), g / dt)


@njit(cache=True, nogil=True)
def _feasible(cx, cy, nx, ny, lim, m, ex, ey, er, nd):
    for j in range(m):
        if cx * nx[j] + cy * ny[j] < -lim[j] - FEASIBLE_TOL:
            return False
    for j in range(nd):
        dx, dy = cx - ex[j], cy - ey[j]
        if math.sqrt(dx * dx + dy * dy) > er[j] + FEASIBLE_TOL:
            return False
    return True


@njit(cache=True, nogil=True)
def nearest_feasible(wx, wy, nx, ny, lim, m, ex, ey, er, nd, out):
    """The point nearest ``(wx, wy)`` with ``c . n_j >= -lim_j`` (j < m) and ``|c - e_j| <= r_j`` (j < nd), into
    ``out``; ``False`` (``out`` untouched) when no candidate is feasible. Exact: the optimum of this convex
    program has at most two active constraints, and every such point is a candidate."""
    best = math.inf
    found = False
    # the wish itself
    if _feasible(wx, wy, nx, ny, lim, m, ex, ey, er, nd):
        out[0], out[1] = wx, wy
        return True
    # one active line: the projection onto it
    for i in range(m):
        t = -lim[i] - (wx * nx[i] + wy * ny[i])
        cx, cy = wx + t * nx[i], wy + t * ny[i]
        d = (cx - wx) ** 2 + (cy - wy) ** 2
        if d < best and _feasible(cx, cy, nx, ny, lim, m, ex, ey, er, nd):
            best, found, out[0], out[1] = d, True, cx, cy
    # one active disc: the radial projection onto its circle
    for i in range(nd):
        dx, dy = wx - ex[i], wy - ey[i]
        dn = math.sqrt(dx * dx + dy * dy)
        if dn > 0.0:
            cx, cy = ex[i] + er[i] * dx / dn, ey[i] + er[i] * dy / dn
            d = (cx - wx) ** 2 + (cy - wy) ** 2
            if d < best and _feasible(cx, cy, nx, ny, lim, m, ex, ey, er, nd):
                best, found, out[0], out[1] = d, True, cx, cy
    # two active lines: their intersection
    for i in range(m):
        for j in range(i + 1, m):
            det = nx[i] * ny[j] - ny[i] * nx[j]
            if abs(det) < 1e-12:
                continue
            cx = (-lim[i] * ny[j] + lim[j] * ny[i]) / det
            cy = (-nx[i] * lim[j] + nx[j] * lim[i]) / det
            d = (cx - wx) ** 2 + (cy - wy) ** 2
            if d < best and _feasible(cx, cy, nx, ny, lim, m, ex, ey, er, nd):
                best, found, out[0], out[1] = d, True, cx, cy
    # a line and a circle
    for i in range(m):
        for j in range(nd):
            s = ex[j] * nx[i] + ey[j] * ny[i] + lim[i]  # signed distance of the centre from the line
            h2 = er[j] * er[j] - s * s
            if h2 < 0.0:
                continue
            h = math.sqrt(h2)
            fx, fy = ex[j] - s * nx[i], ey[j] - s * ny[i]
            for sign in (-1.0, 1.0):
                cx, cy = fx - sign * h * ny[i], fy + sign * h * nx[i]
                d = (cx - wx) ** 2 + (cy - wy) ** 2
                if d < best and _feasible(cx, cy, nx, ny, lim, m, ex, ey, er, nd):
                    best, found, out[0], out[1] = d, True, cx, cy
    # two circles
    for i in range(nd):
        for j in range(i + 1, nd):
            dx, dy = ex[j] - ex[i], ey[j] - ey[i]
            dd = math.sqrt(dx * dx + dy * dy)
            if dd < 1e-12 or dd > er[i] + er[j] or dd < abs(er[i] - er[j]):
                continue
            a = (er[i] * er[i] - er[j] * er[j] + dd * dd) / (2.0 * dd)
            h = math.sqrt(max(er[i] * er[i] - a * a, 0.0))
            px, py = ex[i] + a * dx / dd, ey[i] + a * dy / dd
            for sign in (-1.0, 1.0):
                cx, cy = px - sign * h * dy / dd, py + sign * h * dx / dd
                d = (cx - wx) ** 2 + (cy - wy) ** 2
                if d < best and _feasible(cx, cy, nx, ny, lim, m, ex, ey, er, nd):
                    best, found, out[0], out[1] = d, True, cx, cy
    return found


@njit(cache=True, nogil=True)
def avoid_rows(obs, act, params, layout):
    """In place on ``act`` ``[B, 2]`` (normalised actions): the layer for each row of ``obs`` ``[B, D]``. Rows
    whose observation or action is not finite are left as they are (the policy already returned its safe
    action for those)."""
    own_r, mate_r, vmax, amax = params[P_OWN_RADIUS], params[P_MATE_RADIUS], params[P_MAX_SPEED], params[P_MAX_ACCEL]
    hw, dt, braking = params[P_HALF_WIDTH], params[P_DT], params[P_BRAKING]
    m_obs, m_mate, mate_braking = params[P_OBS_MARGIN], params[P_MATE_MARGIN], params[P_MATE_BRAKING]
    credit = params[P_MATE_CREDIT]
    sp, sv, ob0, n_ob = layout[L_SELF_POS], layout[L_SELF_VEL], layout[L_OBSTACLES], layout[L_N_OBSTACLES]
    tm0, n_tm = layout[L_MATES], layout[L_N_MATES]
    cap = n_tm + 4 + n_ob
    nx = np.empty(cap)
    ny = np.empty(cap)
    lim = np.empty(cap)
    ex = np.empty(2)
    ey = np.empty(2)
    er = np.empty(2)
    out = np.empty(2)
    for b in range(obs.shape[0]):
        finite = math.isfinite(act[b, 0]) and math.isfinite(act[b, 1])
        for i in range(obs.shape[1]):
            if not math.isfinite(obs[b, i]):
                finite = False
                break
        if not finite:
            continue
        x, y = np.float64(obs[b, sp]), np.float64(obs[b, sp + 1])
        m = 0
        for k in range(n_tm):  # teammates: half the budget each
            o = tm0 + k * MATE_COLUMNS
            dx, dy = np.float64(obs[b, o]), np.float64(obs[b, o + 1])
            d = math.sqrt(dx * dx + dy * dy)
            if obs[b, o + 4] > 0.5 and d > 1e-9:
                nx[m], ny[m] = -dx / d, -dy / d
                lim[m] = 0.5 * _limit(d - own_r - mate_r, m_mate, mate_braking, dt)
                away = -(np.float64(obs[b, o + 2]) * nx[m] + np.float64(obs[b, o + 3]) * ny[m])
                if away > 0.0:  # teammate_credit: a share of the teammate's own speed away from this drone
                    lim[m] += credit * away
                m += 1
        for w in range(4):  # walls: +x, -x, +y, -y
            s = 1.0 if w % 2 == 0 else -1.0
            p = x if w < 2 else y
            nx[m] = -s if w < 2 else 0.0
            ny[m] = 0.0 if w < 2 else -s
            lim[m] = _limit(hw - own_r - s * p, m_obs, braking, dt)
            m += 1
        for k in range(n_ob):
            o = ob0 + k * 3
            dx, dy, r = np.float64(obs[b, o]), np.float64(obs[b, o + 1]), np.float64(obs[b, o + 2])
            d = math.sqrt(dx * dx + dy * dy)
            if r > 0.0 and d > 1e-9:
                nx[m], ny[m] = -dx / d, -dy / d
                lim[m] = _limit(d - r - own_r, m_obs, braking, dt)
                m += 1
        wx, wy = np.float64(act[b, 0]) * vmax, np.float64(act[b, 1]) * vmax
        speed = math.sqrt(wx * wx + wy * wy)
        if speed > vmax:  # the world flies at most max_speed: the wish as the world would take it
            wx, wy = wx * vmax / speed, wy * vmax / speed
        ex[0], ey[0], er[0] = 0.0, 0.0, vmax
        ex[1], ey[1], er[1] = np.float64(obs[b, sv]), np.float64(obs[b, sv + 1]), amax * dt * (1.0 - REACH_SHRINK)
        if not nearest_feasible(wx, wy, nx, ny, lim, m, ex, ey, er, 2, out):
            if not nearest_feasible(wx, wy, nx, ny, lim, m, ex, ey, er, 1, out):
                out[0], out[1] = 0.0, 0.0  # unreachable in exact arithmetic: zero is always safe
        act[b, 0] = out[0] / vmax
        act[b, 1] = out[1] / vmax


class Avoidance:
    """The layer for actors of one role: ``apply(obs, act)`` in place, ``obs`` ``[D]`` or ``[B, D]``."""

    def __init__(self, spec: SwarmSpec, role: Role) -> None:
        self.spec = spec
        self.role = Role(role)
        self.params, self.layout = role_tables(spec, self.role)

    def apply(self, obs: np.ndarray, act: np.ndarray) -> np.ndarray:
        o = obs if obs.ndim == 2 else obs.reshape(1, -1)
        a = act if act.ndim == 2 else act.reshape(1, -1)
        avoid_rows(o, a, self.params, self.layout)
        return act


def avoid_agents(spec: SwarmSpec, obs: np.ndarray, act: np.ndarray, agents: np.ndarray | None = None) -> np.ndarray:
    """The layer for every agent column in ``agents`` (default: all) of ``obs`` ``[B, N, D]`` and ``act``
    ``[B, N, 2]`` (in place; a float64 or float32 array), each with its role's tables. A no-op when the spec's
    layer is off."""
    if not spec.avoidance.enabled:
        return act
    roles = spec.roles
    cols = range(len(roles)) if agents is None else [int(i) for i in np.asarray(agents).reshape(-1)]
    tables = {r: role_tables(spec, r) for r in set(roles[i] for i in cols)}
    for i in cols:
        params, layout = tables[roles[i]]
        a = np.ascontiguousarray(act[:, i])
        avoid_rows(obs[:, i], a, params, layout)
        act[:, i] = a
    return act
