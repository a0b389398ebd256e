"""Non-learning baselines and the policy protocol the evaluator runs.

Every policy maps a batch of observations to a batch of actions for *all* agents::

    actions = policy.act(obs, env)      # obs [B, N, D] from PursuitEnv, actions [B, N, 2] in [-1, 1]

``TeamPolicy`` takes the pursuer-team rows (pursuers and scouts) from one policy and the evader rows from
another, so learned pursuers can meet scripted evaders and the other way round.

The classical team is a **centralized, full-information** baseline: it reads the true world state from
``env.state`` (every position, velocity and obstacle), not the agents' observations, whatever the spec's
``observability``. It is the bar that learned policies have to beat, not a deployable controller. One option flies
it on the pursuers' own observations instead (``ClassicalPursuers.information = "observed"``): the bar for a team
trained with partial observability, which knows what each drone senses or hears, and no more.

- pursuers: assigned to evaders by the Hungarian method (scipy's ``linear_sum_assignment`` per env) with
  each evader replicated ``ceil(n_p / n_e)`` times, so each gets about ``n_p / n_e`` pursuers; each flies at
  its evader's position led by the evader's velocity, through an avoidance field (obstacles: slide along
  the surface and a short repulsion; walls: no outward motion; teammates: separation);
- scouts: Lloyd's algorithm, each moves toward the centroid of its own Voronoi cell clipped to the arena
  (every agent a seed, the same cells as the exploration reward), through the same avoidance field;
- evaders (``FleeingEvaders``): flee the pursuers and scouts (inverse-square weighted), repelled by walls,
  obstacles and each other, always at full speed.
"""
from __future__ import annotations

import logging
import math
from typing import Protocol, runtime_checkable

import numpy as np
from scipy.optimize import linear_sum_assignment

from runtime.spec import Role, SwarmSpec
from training.voronoi import bounded_cells

log = logging.getLogger(__name__)

__all__ = ["Policy", "RandomPolicy", "TeamPolicy", "ClassicalPursuers", "FleeingEvaders", "assign_targets",
           "make_policy", "POLICY_NAMES", "EVADER_NAMES"]


@runtime_checkable
class Policy(Protocol):
    """Anything that acts for every agent of a batch of envs.

    ``obs``: ``[B, N, D]`` as returned by ``PursuitEnv.reset/step`` (rows zero-padded to ``spec.max_obs_dim``);
    ``env``: the ``PursuitEnv`` being stepped (full-information baselines read ``env.state``; learned policies
    should use ``obs`` only). Returns ``[B, N, 2]`` in [-1, 1]; rows a policy does not control may be zero.
    """

    def act(self, obs: np.ndarray, env) -> np.ndarray: ...


class RandomPolicy:
    """Uniform random actions in [-1, 1]^2 for every agent, from its own generator."""

    def __init__(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, obs: np.ndarray, env) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, (obs.shape[0], env.n_agents, 2))


class TeamPolicy:
    """Pursuer-team rows (pursuers and scouts) from ``pursuer_team``, evader rows from ``evaders``."""

    def __init__(self, pursuer_team: Policy, evaders: Policy) -> None:
        self.pursuer_team = pursuer_team
        self.evaders = evaders

    def act(self, obs: np.ndarray, env) -> np.ndarray:
        nt = env.spec.team.n_team
        out = np.asarray(self.pursuer_team.act(obs, env), dtype=np.float64).copy()
        out[:, nt:] = np.asarray(self.evaders.act(obs, env), dtype=np.float64)[:, nt:]
        return out


# --------------------------------------------------------------------------------------------------
# pure helpers


def assign_targets(pursuer_pos: np.ndarray, target_pos: np.ndarray) -> np.ndarray:
    """Hungarian assignment of pursuers ``[B, P, 2]`` to targets ``[B, E, 2]``, minimizing total distance.

    Each target is offered ``ceil(P / E)`` slots, so with ``P >= E`` every target gets at least one pursuer
    and none gets more than ``ceil(P / E)``. Returns the target index of every pursuer ``[B, P]``.
    """
    b, p = pursuer_pos.shape[:2]
    e = target_pos.shape[1]
    out = np.zeros((b, p), dtype=np.int64)
    if p == 0 or e == 0:
        return out
    k = math.ceil(p / e)
    d = np.linalg.norm(pursuer_pos[:, :, None, :] - target_pos[:, None, :, :], axis=-1)  # [B, P, E]
    slot_target = np.repeat(np.arange(e), k)  # [E * k]
    cost = d[:, :, slot_target]  # [B, P, E * k]
    for i in range(b):
        rows, cols = linear_sum_assignment(cost[i])
        out[i, rows] = slot_target[cols]
    return out


def local_assign_targets(team_pos: np.ndarray, pursuers: np.ndarray, target_pos: np.ndarray,
                         n_mates: int) -> np.ndarray:
    """Each pursuer's target ``[B, P]`` by its own ``assign_targets`` over itself and its ``n_mates`` nearest
    teammates ``team_pos`` ``[B, T, 2]`` (pursuers and scouts alike, nearest first, ties to the lower index: the
    teammates a full-observability observation lists, which do not say their role), taking its own row. A function
    of what one pursuer observes, so that a decentralized student can learn it; the classical team's
    ``assign_targets`` over every pursuer reads the whole state. ``pursuers``: the pursuers' indices into
    ``team_pos``. With two targets it is solved in closed form (the group's members whose distance to target 0
    minus that to target 1 is among the ``c`` smallest go to target 0, ``c`` the number of negative differences
    clipped to the slots ``[m - ceil(m / 2), ceil(m / 2)]``: the same optimum as the Hungarian method)."""
    b, t = team_pos.shape[:2]
    p, e = pursuers.size, target_pos.shape[1]
    if p == 0 or e <= 1:
        return np.zeros((b, p), dtype=np.int64)
    own = team_pos[:, pursuers]  # [B, P, 2]
    dm = np.linalg.norm(own[:, :, None] - team_pos[:, None], axis=-1)  # [B, P, T]
    dm[:, np.arange(p), pursuers] = np.inf
    k = min(n_mates, t - 1)
    near = np.argsort(dm, axis=2, kind="stable")[:, :, :k]  # [B, P, k]
    group = np.concatenate([own[:, :, None], np.take_along_axis(team_pos[:, None], near[..., None], axis=2)],
                           axis=2)  # [B, P, m, 2]: oneself first
    m = k + 1
    if e == 2:
        slots = math.ceil(m / 2)
        d = np.linalg.norm(group[:, :, :, None] - target_pos[:, None, None], axis=-1)  # [B, P, m, 2]
        diff = d[..., 0] - d[..., 1]  # [B, P, m]
        c = np.clip((diff < 0).sum(-1), m - slots, slots)  # [B, P]
        rank = (diff < diff[..., :1]).sum(-1)  # own rank among the group (oneself first on ties)
        return np.where(rank < c, 0, 1).astype(np.int64)
    targets = np.broadcast_to(target_pos[:, None], (b, p, e, 2)).reshape(b * p, e, 2)
    return assign_targets(group.reshape(b * p, m, 2), targets)[:, 0].reshape(b, p)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.sqrt((v * v).sum(-1, keepdims=True))
    return v / np.maximum(n, 1e-9)


def _fade_in(d: np.ndarray, start: float, band: float) -> np.ndarray:
    """0 at distances ``d`` up to ``start``, 1 from ``start + band`` on, linear in between."""
    return np.clip((d - start) / band, 0.0, 1.0)


def _to_wall(p: np.ndarray, half_width: float) -> np.ndarray:
    """Distance ``[..., 1]`` from points ``p`` ``[..., 2]`` to the nearest wall of the arena."""
    return (half_width - np.abs(p)).min(-1, keepdims=True)


def _clip_norm(v: np.ndarray, limit: float = 1.0) -> np.ndarray:
    n = np.sqrt((v * v).sum(-1, keepdims=True))
    return v * np.minimum(1.0, limit / np.maximum(n, 1e-12))


def _perp_towards(n: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The unit perpendicular of ``n`` that points along ``ref`` (ties: counter-clockwise)."""
    t = np.stack([-n[..., 1], n[..., 0]], axis=-1)
    s = np.where((t * ref).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    return t * s


def avoid_obstacles(pos: np.ndarray, v: np.ndarray, radius: np.ndarray, obstacle_pos: np.ndarray,
                    obstacle_radius: np.ndarray, reach: float, repulsion: float,
                    side_softness: float = 0.0) -> np.ndarray:
    """Bends the velocity wish ``v`` ``[B, M, 2]`` around circular obstacles.

    Within ``reach`` [m] of an obstacle's surface the inward part of ``v`` is turned into motion along the
    surface (the side ``v`` already leans to), in proportion to closeness, plus a repulsion growing to
    ``repulsion`` at contact. ``radius`` ``[M]``: the agents' body radii. ``side_softness`` > 0: the motion along
    the surface is scaled by ``tanh(lean / side_softness)``, ``lean`` the sine of the angle between ``v`` and the
    surface normal (signed by side), so that it fades to nothing instead of flipping side when ``v`` points
    straight at the obstacle's centre: a continuous function of the positions, which a learned clone can follow.
    """
    if obstacle_pos.shape[1] == 0:
        return v
    d = pos[:, :, None, :] - obstacle_pos[:, None, :, :]  # [B, M, K, 2]
    dist = np.sqrt((d * d).sum(-1))
    n = d / np.maximum(dist, 1e-9)[..., None]
    surface = dist - obstacle_radius[:, None, :] - radius[None, :, None]
    w = np.clip(1.0 - surface / reach, 0.0, 1.0)  # [B, M, K]
    vk = v[:, :, None, :]
    inward = np.maximum(-(vk * n).sum(-1), 0.0)  # speed toward the obstacle
    if side_softness > 0:
        t0 = np.stack([-n[..., 1], n[..., 0]], axis=-1)
        lean = (t0 * vk).sum(-1) / np.maximum(np.sqrt((vk * vk).sum(-1)), 1e-12)
        t = t0 * np.tanh(lean / side_softness)[..., None]
    else:
        t = _perp_towards(n, vk)
    return v + ((w * inward + repulsion * w * w)[..., None] * n + (w * inward)[..., None] * t).sum(2)


def wall_field(pos: np.ndarray, v: np.ndarray, radius: np.ndarray, hw: float, reach: float,
               repulsion: float) -> np.ndarray:
    """Within ``reach`` [m] of a wall: cancels the outward part of ``v`` in proportion to closeness and adds a
    repulsion growing quadratically to ``repulsion`` at the wall."""
    gap = hw - radius[None, :, None] - np.abs(pos)  # [B, M, 2]
    w = np.clip(1.0 - gap / reach, 0.0, 1.0)
    side = np.sign(pos)
    outward = np.maximum(v * side, 0.0)
    return v - side * outward * w - side * repulsion * w * w


def separation(pos: np.ndarray, others: np.ndarray, reach: float, gain: float,
               same: bool = True) -> np.ndarray:
    """Push ``[B, M, 2]`` away from ``others`` ``[B, O, 2]`` closer than ``reach`` [m], linear in closeness.
    ``same``: ``others`` is ``pos`` itself (the zero self-distance is ignored)."""
    d = pos[:, :, None, :] - others[:, None, :, :]
    dist = np.sqrt((d * d).sum(-1))
    w = np.clip(1.0 - dist / reach, 0.0, 1.0)
    if same:
        w = np.where(dist > 1e-12, w, 0.0)
    return gain * ((w / np.maximum(dist, 1e-9))[..., None] * d).sum(2)


# --------------------------------------------------------------------------------------------------
# policies


class ClassicalPursuers:
    """Hungarian pursuit and Lloyd scouting for the pursuer team; evader rows are zero.

    Reads ``env.state`` (centralized, full information). Gains are in units of normalized action.
    """

    lead_time_max = 0.6
    """Longest look-ahead [s] when leading an evader: ``min(distance / own speed, lead_time_max)``."""
    lead_time_others: float | None = None
    """None (the classical team): every pursuer leads by ``lead_time_max``. A number: only the pursuer nearest its
    target among those assigned to it leads by ``lead_time_max``; the others lead by this longer or shorter
    look-ahead [s] (``train.teacher_lead_others``: the first closes in, the rest head for where the target goes)."""
    lead_side_time: float | None = None
    """None (the classical team): the look-ahead does not depend on where the target flies. A number [s]: the
    look-ahead shrinks from ``lead_time_max`` (or ``lead_time_others``) while the target flies along the bearing from
    the pursuer to it, to this one as its velocity turns ``lead_side_angle`` off that bearing (linear in the angle's
    cosine; beyond it, and toward the pursuer, this one): a target running sideways is led less, as it may turn back
    (``train.teacher_side_lead``; full information only)."""
    lead_side_angle = 60.0
    """The angle [deg] between the target's velocity and the bearing from the pursuer at which the look-ahead reaches
    ``lead_side_time`` (``train.teacher_side_angle``)."""
    lead_side_wall: float | None = None
    """None: the side lead applies wherever the target is. A number [m]: only to a target at least this far plus
    ``lead_side_fade`` from every wall, fading (linear) to none at this distance, so that a target whose path a wall
    bends is led by ``lead_time_max`` (``train.teacher_side_wall``)."""
    lead_side_fade = 0.3
    """The band [m] over which ``lead_side_wall`` fades the side lead out toward the walls."""
    obstacle_reach = 0.3
    """Distance from an obstacle's surface [m] where avoidance starts."""
    obstacle_repulsion = 0.5
    """Repulsion at an obstacle's surface [normalized action]."""
    wall_reach: float | None = None
    """Distance from a wall [m] where outward motion is damped (pursuers follow evaders to the wall). None: one
    drone diameter, twice the team's largest radius from the spec (``wall_reach_for``; 0.15 m by default)."""
    separation_reach = 0.5
    """Centre distance [m] under which teammates push apart (contact is at R_i + R_j, 0.15 m by default)."""
    separation_gain = 3.0
    """Teammate push at zero distance [normalized action]."""
    lloyd_gain = 2.0
    """Scouts' commanded speed per metre to their cell's centroid [1/s, normalized action]."""
    scout_sweep: float | None = None
    """None (the classical team): the scouts take Lloyd's step alone and settle at their cells' centroids. A number
    [normalized action]: added to Lloyd's step, a wish of this size that keeps the scouts moving, so that the team
    sees more of the arena over an episode (``scout_sweep_mode``; ``train.teacher_scout_sweep``)."""
    scout_sweep_wall: float | None = None
    """None: ``scout_sweep`` applies wherever the scout is. A number [m]: only to a scout at least this far plus
    ``scout_sweep_fade`` from every wall, fading (linear) to none at this distance, so that the sweep does not carry
    the scouts along the walls, where a runner keeping to them meets them (results/issue13/teacher_scout_sweep.py; no
    ``[train]`` option: it did not help the perimeter runner at the teacher)."""
    scout_sweep_fade = 0.3
    """The band [m] over which ``scout_sweep_wall`` and ``scout_sweep_clear`` fade the sweep out."""
    scout_sweep_clear: float | None = None
    """None: ``scout_sweep`` applies however near the evaders the scout is. A number [m]: only to a scout at least
    this far plus ``scout_sweep_fade`` from every evader, fading (linear) to none at this distance, so that near a
    chase the scouts hold Lloyd's spread and sweep the rest of the arena (``train.teacher_scout_sweep_clear``)."""
    scout_sweep_mode = "heading"
    """What ``scout_sweep`` adds: "heading": along the scout's own velocity (none at rest); "orbit": counter-clockwise
    about the arena's centre (tangent to the circle through the scout, faded in over the 0.5 m around the centre)."""
    obstacle_side_softness = 0.0
    """``avoid_obstacles``' ``side_softness`` for the team: 0 (the classical team): slide to the side the wish leans
    to, flipping side when it points straight at the obstacle's centre; > 0: fade the slide out there instead
    (``train.teacher_obstacle_softness``)."""
    assignment = "central"
    """How the pursuers split between the evaders: "central" (the classical team, the bar): one Hungarian
    assignment over every pursuer; "local": each pursuer's own over itself and the teammates its observation lists
    (``local_assign_targets``), for a teacher whose choice of target a decentralized student can learn."""

    information = "full"
    """What the pursuers know of the targets: "full" (the classical team, the bar): the true state; "observed": each
    pursuer only what its own observation holds (``runtime.observation``'s one encoder: the ``targets`` field's last
    known position and velocity, and the team's split from the ``assigned`` field, so that it needs
    ``sensing.share_assignment``), flying at the last known position carried forward by the sighting's age, and, knowing
    no target, searching as a scout does (Lloyd's step). With full observability it acts as "full" does; with
    ``sensing.observability = "partial"`` it is the classical team on a drone's own knowledge: the fair bar for a
    partial-observability team (results/issue13/classical_partial.py)."""

    def act(self, obs: np.ndarray, env) -> np.ndarray:
        spec: SwarmSpec = env.spec
        s = env.state
        t = spec.team
        b = s.pos.shape[0]
        nt = t.n_team
        out = np.zeros((b, t.n_agents, 2))
        radius = np.asarray(spec.per_agent("radius"))
        hw = spec.arena.half_width
        team_pos = s.pos[:, :nt]
        wish = np.zeros((b, nt, 2))
        p = np.asarray(t.indices(Role.PURSUER))
        sc = np.asarray(t.indices(Role.SCOUT))
        if self.information not in ("full", "observed"):
            raise ValueError(f"ClassicalPursuers.information: {self.information!r} is not 'full' or 'observed'")
        centroids = bounded_cells(s.pos, hw)[1] if sc.size or self.information == "observed" else None
        if p.size and self.information == "observed":
            wish[:, p] = self._pursue_observed(spec, obs[:, p], s.pos[:, p], centroids[:, p])
        elif p.size:
            target = None
            if self.assignment == "local":
                target = local_assign_targets(team_pos, p, s.pos[:, nt:], spec.sensing.n_teammates_observed)
            elif self.assignment != "central":
                raise ValueError(f"ClassicalPursuers.assignment: {self.assignment!r} is not 'central' or 'local'")
            wish[:, p] = self._pursue(spec, s.pos[:, p], s.pos[:, nt:], s.vel[:, nt:], target)
        if sc.size:
            wish[:, sc] = _clip_norm(self.lloyd_gain * (centroids[:, sc] - s.pos[:, sc])
                                     + self._sweep(s.pos[:, sc], s.vel[:, sc], hw, s.pos[:, nt:]))
        v = wish + separation(team_pos, team_pos, self.separation_reach, self.separation_gain)
        v = avoid_obstacles(team_pos, v, radius[:nt], s.obstacle_pos, s.obstacle_radius,
                            self.obstacle_reach, self.obstacle_repulsion, self.obstacle_side_softness)
        v = wall_field(team_pos, v, radius[:nt], hw, self.wall_reach_for(spec), 0.0)
        out[:, :nt] = _clip_norm(v)
        return out

    def _sweep(self, pos: np.ndarray, vel: np.ndarray, half_width: float,
               evaders: np.ndarray | None = None) -> np.ndarray | float:
        """``scout_sweep``'s wish ``[B, S, 2]`` for scouts at ``pos`` flying at ``vel`` in an arena of ``half_width``
        with the evaders at ``evaders`` ``[B, E, 2]`` (0 when it is None)."""
        if self.scout_sweep is None:
            return 0.0
        size = self.scout_sweep
        if self.scout_sweep_wall is not None:
            size = size * _fade_in(_to_wall(pos, half_width), self.scout_sweep_wall, self.scout_sweep_fade)
        if self.scout_sweep_clear is not None and evaders is not None and evaders.shape[1]:
            gap = np.linalg.norm(pos[:, :, None] - evaders[:, None], axis=-1).min(-1, keepdims=True)
            size = size * _fade_in(gap, self.scout_sweep_clear, self.scout_sweep_fade)
        if self.scout_sweep_mode == "heading":
            return size * _unit(vel)
        if self.scout_sweep_mode == "orbit":
            r = np.linalg.norm(pos, axis=-1, keepdims=True)
            tangent = np.stack([-pos[..., 1], pos[..., 0]], -1) / np.maximum(r, 1e-9)
            return size * np.clip(r / 0.5, 0.0, 1.0) * tangent
        raise ValueError(f"ClassicalPursuers.scout_sweep_mode: {self.scout_sweep_mode!r} is not 'heading' or 'orbit'")

    def wall_reach_for(self, spec: SwarmSpec) -> float:
        """``wall_reach`` [m], or when it is None one drone diameter of ``spec``'s pursuer team."""
        if self.wall_reach is not None:
            return self.wall_reach
        return 2.0 * max(spec.per_agent("radius")[:spec.team.n_team])

    def _pursue_observed(self, spec: SwarmSpec, obs: np.ndarray, pp: np.ndarray, centroids: np.ndarray) -> np.ndarray:
        """``information = "observed"``: the pursuers' wishes ``[B, P, 2]`` from their observations ``obs``
        ``[B, P, D]`` alone (positions ``pp`` and Lloyd ``centroids`` only for those that know no target)."""
        lay = spec.layout(Role.PURSUER)
        if "assigned" not in lay.names():
            raise ValueError("ClassicalPursuers.information = 'observed' takes the team's split from the observation's "
                             "`assigned` field: set sensing.share_assignment = true in the spec")
        field = lay["targets"]
        col = {c: i for i, c in enumerate(field.columns)}  # dx, dy, vx, vy, age, known (runtime.spec)
        rel, vel = [col["dx"], col["dy"]], [col["vx"], col["vy"]]
        tg = obs[..., field.slice].reshape(obs.shape[:2] + (field.rows, len(field.columns)))  # [B, P, E, columns]
        mine = obs[..., lay["assigned"].slice] > 0.5  # [B, P, E]
        known = tg[..., col["known"]] > 0.5
        dist = np.linalg.norm(tg[..., rel], axis=-1)
        # the assigned target; a known one without a split (not possible with two targets known): the nearest
        choice = np.where(mine.any(-1), mine.argmax(-1), np.where(known, dist, np.inf).argmin(-1))  # [B, P]
        pick = np.take_along_axis(tg, choice[..., None, None], axis=2)[:, :, 0]  # [B, P, columns]
        d = np.linalg.norm(pick[..., rel], axis=-1, keepdims=True)
        lead = np.minimum(d / spec.pursuer.max_speed, self.lead_time_max)
        hw = spec.arena.half_width
        goal = np.clip(pp + pick[..., rel] + pick[..., vel] * (pick[..., col["age"]][..., None] + lead), -hw, hw)
        chase = _unit(goal - pp)
        search = _clip_norm(self.lloyd_gain * (centroids - pp))
        return np.where(known.any(-1, keepdims=True), chase, search)

    def _pursue(self, spec: SwarmSpec, pp: np.ndarray, ep: np.ndarray, ev: np.ndarray,
                target: np.ndarray | None = None) -> np.ndarray:
        """Unit velocity wishes ``[B, P, 2]`` of the pursuers toward their assigned evaders (``target`` ``[B, P]``;
        None: ``assign_targets``), led."""
        if target is None:
            target = assign_targets(pp, ep)  # [B, P]
        bi = np.arange(pp.shape[0])[:, None]
        tp = ep[bi, target]
        tv = ev[bi, target]
        dist = np.linalg.norm(tp - pp, axis=-1, keepdims=True)
        lmax = self.lead_time_max
        if self.lead_time_others is not None:
            same = target[:, :, None] == target[:, None, :]  # [B, P, P]: pursuers sharing a target
            ahead = same & (dist[:, None, :, 0] < dist[:, :, None, 0])  # ... that are nearer it (ties: neither)
            lmax = np.where(ahead.any(-1, keepdims=True), self.lead_time_others, self.lead_time_max)
        if self.lead_side_time is not None:
            speed = np.linalg.norm(tv, axis=-1, keepdims=True)
            along = (tv * (tp - pp)).sum(-1, keepdims=True) / np.maximum(dist * speed, 1e-9)  # cos of the angle
            along = np.where(speed > 1e-6, along, 1.0)  # a target at rest: along the bearing
            c0 = np.cos(np.radians(self.lead_side_angle))
            side = np.clip((1.0 - along) / (1.0 - c0), 0.0, 1.0)
            if self.lead_side_wall is not None:
                side = side * _fade_in(_to_wall(tp, spec.arena.half_width), self.lead_side_wall, self.lead_side_fade)
            lmax = lmax - (lmax - self.lead_side_time) * side
        lead = np.minimum(dist / spec.pursuer.max_speed, lmax)
        hw = spec.arena.half_width
        goal = np.clip(tp + tv * lead, -hw, hw)
        return _unit(goal - pp)


class FleeingEvaders:
    """Evaders flee the pursuer team, repelled by walls, obstacles and each other; team rows are zero.

    Reads ``env.state`` (full information).
    """

    threat_softening = 0.2
    """Added to threat distances [m] in the inverse-square weighting, so the nearest does not dominate to
    infinity."""
    wall_reach = 0.8
    """Distance from a wall [m] where the evader starts to turn away (corners are where it gets caught)."""
    wall_repulsion = 1.5
    """Repulsion at a wall [normalized action]."""
    obstacle_reach = 0.3
    """Distance from an obstacle's surface [m] where avoidance starts."""
    obstacle_repulsion = 0.5
    """Repulsion at an obstacle's surface [normalized action]."""
    separation_reach = 0.3
    """Evader-evader centre distance [m] under which they push apart."""

    def act(self, obs: np.ndarray, env) -> np.ndarray:
        spec: SwarmSpec = env.spec
        s = env.state
        nt = spec.team.n_team
        b, n = s.pos.shape[:2]
        out = np.zeros((b, n, 2))
        ep = s.pos[:, nt:]
        d = ep[:, :, None, :] - s.pos[:, None, :nt, :]  # [B, E, T, 2] from threats to evader
        dist = np.sqrt((d * d).sum(-1))
        w = 1.0 / (dist + self.threat_softening) ** 2
        flee = _unit(((w / np.maximum(dist, 1e-9))[..., None] * d).sum(2))
        radius = np.asarray(spec.per_agent("radius"))[nt:]
        v = flee + separation(ep, ep, self.separation_reach, 1.5)
        v = wall_field(ep, v, radius, spec.arena.half_width, self.wall_reach, self.wall_repulsion)
        v = avoid_obstacles(ep, v, radius, s.obstacle_pos, s.obstacle_radius, self.obstacle_reach,
                            self.obstacle_repulsion)
        out[:, nt:] = _unit(v)
        return out


POLICY_NAMES = ("random", "classical")
EVADER_NAMES = ("classical", "random")


def make_policy(name: str, seed: int | None = None, evaders: str = "classical") -> TeamPolicy:
    """A named pursuer team (``POLICY_NAMES``) against named evaders (``EVADER_NAMES``: "classical" = fleeing).

    ``seed`` seeds the random generators of random policies.
    """
    if name == "random":
        team: Policy = RandomPolicy(seed)
    elif name == "classical":
        team = ClassicalPursuers()
    else:
        raise ValueError(f"unknown policy {name!r}: use one of {list(POLICY_NAMES)}")
    if evaders == "classical":
        ev: Policy = FleeingEvaders()
    elif evaders == "random":
        ev = RandomPolicy(None if seed is None else seed + 1)
    else:
        raise ValueError(f"unknown evader policy {evaders!r}: use one of {list(EVADER_NAMES)}")
    return TeamPolicy(team, ev)
