"""Which drone flies which trained actor.

The model manifest lists actors (``{"id": "pursuer_0", "role": "pursuer"}``, ...). ``assign_roles`` maps them
onto the drones present; ``reassign`` repairs the mapping when drones drop out or run low on battery. Both
are pure: they return new ``Assignment`` objects and, for ``reassign``, the list of changes, each of which is
also logged.

Teams: pursuer and scout actors are flown by drones of the pursuer team; evader actors by evader drones
(in the simulator demo the evaders are simulated drones too). A drone never flies two actors and an actor is
never flown by two drones.

Initial cost (minimised with the Hungarian method, ``scipy.optimize.linear_sum_assignment``):

- pursuer actors come first: each carries a bonus of ``-PRIORITY`` so that when there are fewer drones than
  actors, pursuers are the ones flown (the paper's assumption (a): at least one pursuer per evader);
- a pursuer actor on drone ``d`` costs ``-battery_d * W_BATTERY + dist(d, nearest evader drone) * W_DISTANCE``
  (normalised by ``distance_scale``, by default the side of the spec's arena): the fullest batteries and the drones nearest the evaders chase;
  scouts cost nothing, so they get the rest (the emptiest batteries, the ones far away);
- ties break by drone and actor order, so the result is deterministic.

Repair (``reassign``): drones that are unavailable or below ``low_battery`` are released and their actors
become vacant. Vacant pursuer actors are filled first by idle drones, then by scouts (a scout drone takes
the pursuer actor and its scout actor becomes vacant); vacant scout actors are then filled by any idle drones
left. Drones that keep flying keep their actors unless they are promoted.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from runtime.spec import Role, SpecError, SwarmSpec

log = logging.getLogger(__name__)

PRIORITY = 1e3
"""Cost bonus of a pursuer actor over a scout actor (dominates every other term)."""
W_BATTERY = 1.0
"""Weight of the battery fraction in a pursuer actor's cost."""
W_DISTANCE = 0.5
"""Weight of the distance to the nearest evader drone (over ``distance_scale``) in a pursuer actor's cost."""

PURSUER_TEAM = "pursuer"
EVADER_TEAM = "evader"


@dataclass(frozen=True)
class Actor:
    """One trained actor of the manifest."""

    id: str
    role: Role

    @property
    def team(self) -> str:
        return EVADER_TEAM if self.role is Role.EVADER else PURSUER_TEAM


@dataclass(frozen=True)
class DroneInfo:
    """What role assignment needs to know about one drone."""

    id: str
    position: tuple[float, ...] = (0.0, 0.0, 0.0)
    """Measured position [m] (x, y[, z])."""
    battery: float = 1.0
    """State of charge, fraction in [0, 1]."""
    available: bool = True
    """Connected, with fresh telemetry and not landed by a failsafe."""
    team: str = PURSUER_TEAM
    """``"pursuer"`` (flies pursuer and scout actors) or ``"evader"`` (flies evader actors)."""


@dataclass(frozen=True)
class RoleChange:
    """One change to an assignment."""

    drone_id: str | None
    """The drone whose actor changed (None when an actor became vacant with no drone to take it)."""
    old_actor: str | None
    new_actor: str | None
    reason: str

    def describe(self) -> str:
        return f"drone {self.drone_id}: {self.old_actor or '-'} -> {self.new_actor or '-'} ({self.reason})"


@dataclass(frozen=True)
class Assignment:
    """Actor id -> drone id, plus the actors (in manifest order) and the actors left without a drone."""

    actors: tuple[Actor, ...]
    by_actor: Mapping[str, str] = field(default_factory=dict)

    def drone_of(self, actor_id: str) -> str | None:
        return self.by_actor.get(actor_id)

    @property
    def by_drone(self) -> dict[str, str]:
        """Drone id -> actor id."""
        return {d: a for a, d in self.by_actor.items()}

    def role_of_drone(self, drone_id: str) -> Role | None:
        a = self.by_drone.get(drone_id)
        return None if a is None else self._actor(a).role

    def count(self, role: Role) -> int:
        """Actors of ``role`` that are flown."""
        return sum(1 for a in self.actors if a.role is role and a.id in self.by_actor)

    @property
    def vacant(self) -> tuple[str, ...]:
        """Actors without a drone, in manifest order."""
        return tuple(a.id for a in self.actors if a.id not in self.by_actor)

    def _actor(self, actor_id: str) -> Actor:
        for a in self.actors:
            if a.id == actor_id:
                return a
        raise KeyError(actor_id)


def parse_actors(manifest_agents: Iterable[Mapping[str, Any] | Actor]) -> tuple[Actor, ...]:
    """Manifest entries ``{"id": ..., "role": ...}`` as ``Actor`` s; raises ``SpecError`` naming the entry."""
    out: list[Actor] = []
    seen: set[str] = set()
    for i, entry in enumerate(manifest_agents):
        if isinstance(entry, Actor):
            actor = entry
        else:
            if not isinstance(entry, Mapping) or "id" not in entry or "role" not in entry:
                raise SpecError(f"manifest.agents[{i}]: expected a table with 'id' and 'role', got {entry!r}")
            role = entry["role"] if isinstance(entry["role"], Role) else Role.parse(str(entry["role"]))
            actor = Actor(str(entry["id"]), role)
        if actor.id in seen:
            raise SpecError(f"manifest.agents[{i}].id: actor {actor.id!r} is listed twice")
        seen.add(actor.id)
        out.append(actor)
    return tuple(out)


def _usable(d: DroneInfo, low_battery: float) -> bool:
    return bool(d.available) and math.isfinite(d.battery) and d.battery >= low_battery


def _xy(d: DroneInfo) -> np.ndarray:
    p = np.asarray(d.position, dtype=float).reshape(-1)[:2]
    return p if p.shape == (2,) and np.all(np.isfinite(p)) else np.zeros(2)


def _pursuit_cost(d: DroneInfo, evader_xy: np.ndarray, distance_scale: float) -> float:
    cost = -W_BATTERY * min(max(d.battery, 0.0), 1.0)
    if len(evader_xy):
        dist = float(np.min(np.hypot(*(evader_xy - _xy(d)).T)))
        cost += W_DISTANCE * dist / distance_scale
    return cost


def arena_side() -> float:
    """The side [m] of the default spec's square arena (``runtime.spec``)."""
    return 2.0 * SwarmSpec().arena.half_width


def _evader_positions(drones: Sequence[DroneInfo], low_battery: float) -> np.ndarray:
    return np.array([_xy(d) for d in drones if d.team == EVADER_TEAM and _usable(d, low_battery)]).reshape(-1, 2)


def assign_roles(manifest_agents: Iterable[Mapping[str, Any] | Actor], drones: Sequence[DroneInfo], *,
                 low_battery: float = 0.2, distance_scale: float | None = None) -> Assignment:
    """Initial assignment of the manifest's actors to the usable drones (available, battery >= ``low_battery``)
    by the cost in the module docstring. ``distance_scale`` [m] normalises distances (None: the side of the
    default spec's arena; the flight session passes its fence's)."""
    distance_scale = arena_side() if distance_scale is None else distance_scale
    actors = parse_actors(manifest_agents)
    _check_drones(drones)
    evader_xy = _evader_positions(drones, low_battery)
    by_actor: dict[str, str] = {}
    for team in (PURSUER_TEAM, EVADER_TEAM):
        team_actors = [a for a in actors if a.team == team]
        team_drones = [d for d in drones if d.team == team and _usable(d, low_battery)]
        if not team_actors or not team_drones:
            continue
        cost = np.zeros((len(team_drones), len(team_actors)))
        for j, a in enumerate(team_actors):
            if a.role is Role.PURSUER:
                cost[:, j] = [-PRIORITY + _pursuit_cost(d, evader_xy, distance_scale) for d in team_drones]
        rows, cols = linear_sum_assignment(cost)
        for r, c in zip(rows, cols):
            by_actor[team_actors[c].id] = team_drones[r].id
    result = Assignment(actors, by_actor)
    for a in actors:
        d = by_actor.get(a.id)
        log.info("role assignment: actor %s (%s) -> drone %s", a.id, a.role.label, d or "none (no drone left)")
    _warn_assumption_a(result, sum(1 for a in actors if a.role is Role.EVADER))
    return result


def reassign(assignment: Assignment, drones: Sequence[DroneInfo], n_evaders: int, *, low_battery: float = 0.2,
             distance_scale: float | None = None) -> tuple[Assignment, list[RoleChange]]:
    """Repair ``assignment`` after dropouts and low batteries (see the module docstring). ``n_evaders`` is the
    number of evaders in play; with at least that many usable pursuer-team drones (and pursuer actors) the
    result flies at least ``n_evaders`` pursuers. Returns the new assignment and the changes, all logged.
    ``distance_scale`` as in ``assign_roles``."""
    distance_scale = arena_side() if distance_scale is None else distance_scale
    _check_drones(drones)
    info = {d.id: d for d in drones}
    by_actor = dict(assignment.by_actor)
    roles = {a.id: a for a in assignment.actors}
    changes: list[RoleChange] = []

    # 1. release drones that are gone, unavailable or low
    for actor_id, drone_id in list(by_actor.items()):
        d = info.get(drone_id)
        if d is None or not d.available:
            reason = "drone gone" if d is None else "drone unavailable"
        elif not (math.isfinite(d.battery) and d.battery >= low_battery):
            reason = f"battery {d.battery:.2f} below {low_battery:.2f}"
        else:
            continue
        del by_actor[actor_id]
        changes.append(RoleChange(drone_id, actor_id, None, reason))

    busy = set(by_actor.values())
    evader_xy = _evader_positions(drones, low_battery)

    def idle(team: str) -> list[DroneInfo]:
        free = [d for d in drones if d.team == team and d.id not in busy and _usable(d, low_battery)]
        return sorted(free, key=lambda d: (_pursuit_cost(d, evader_xy, distance_scale), d.id))

    def take(actor_id: str, d: DroneInfo, old: str | None, reason: str) -> None:
        by_actor[actor_id] = d.id
        busy.add(d.id)
        changes.append(RoleChange(d.id, old, actor_id, reason))

    # 2. vacant pursuer actors: idle drones first, then promoted scouts
    for a in assignment.actors:
        if a.role is not Role.PURSUER or a.id in by_actor:
            continue
        spare = idle(PURSUER_TEAM)
        if spare:
            take(a.id, spare[0], None, "idle drone fills a vacant pursuer actor")
            continue
        scouts = sorted(((info[d], s) for s, d in by_actor.items() if roles[s].role is Role.SCOUT),
                        key=lambda ds: (_pursuit_cost(ds[0], evader_xy, distance_scale), ds[0].id))
        if scouts:
            d, scout_actor = scouts[0]
            del by_actor[scout_actor]
            take(a.id, d, scout_actor, "scout promoted to a vacant pursuer actor")

    # 3. vacant scout and evader actors from whatever idle drones are left
    for a in assignment.actors:
        if a.id in by_actor or a.role is Role.PURSUER:
            continue
        spare = idle(a.team)
        if spare:  # scouts take the drone least suited to pursuit (emptiest battery, farthest away)
            take(a.id, spare[-1] if a.role is Role.SCOUT else spare[0], None,
                 f"idle drone fills a vacant {a.role.label} actor")

    result = Assignment(assignment.actors, by_actor)
    for c in changes:
        log.info("role change: %s", c.describe())
    _warn_assumption_a(result, n_evaders)
    return result, changes


def _check_drones(drones: Sequence[DroneInfo]) -> None:
    ids = [d.id for d in drones]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise ValueError(f"drone ids must be unique, {dup} appear more than once")
    for d in drones:
        if d.team not in (PURSUER_TEAM, EVADER_TEAM):
            raise ValueError(f"drone {d.id}: team {d.team!r} is not 'pursuer' or 'evader'")


def _warn_assumption_a(a: Assignment, n_evaders: int) -> None:
    n_p = a.count(Role.PURSUER)
    if n_p < n_evaders:
        log.warning("role assignment: only %d pursuers for %d evaders: the policy's assumption (a) (at least one "
                    "pursuer per evader) does not hold; add drones or land evaders", n_p, n_evaders)
