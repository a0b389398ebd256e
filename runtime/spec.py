"""The single definition of every number that crosses a package boundary.

Training, export, the per-drone runtime, the ground station and the C generator all read the arena, the
agents' radii and speeds, the sensing and communication ranges, the team composition and the observation
and action layout from here. ``SwarmSpec.hash`` is a version hash over all of it; it is stored in every
exported model and checked when a model is loaded.

Agents are always ordered ``[pursuers..., scouts..., evaders...]``.

Observation layout (per observer, all in the world frame, SI units; see ``ObsLayout``):

pursuers and scouts (the "pursuer team")
    ``self_pos``   [2]        own position x, y [m]
    ``self_vel``   [2]        own velocity vx, vy [m/s]
    ``obstacles``  [K_o x 3]  every obstacle sorted by surface distance: dx, dy to its centre [m], radius [m]
    ``targets``    [E x 6]    each evader, in fixed identity order, as this agent knows it (own sensing or
                              relayed by teammates): dx, dy to its last known position [m], its last known
                              vx, vy [m/s], age of that sighting [s], known flag (1 = known, 0 = never seen
                              or older than ``sensing.target_memory``; the other five are then 0 except
                              age = target_memory)
    ``teammates``  [K_m x 5]  the nearest teammates within comm range: dx, dy [m], vx, vy [m/s], valid flag
    ``assigned``   [E x 1]    only with ``sensing.share_assignment``: 1 for the target this agent takes in the
                              team's split, else 0 (scouts: all 0). The agent splits the pursuers it hears (every
                              pursuer with full observability; itself always) between the targets it knows as the
                              classical team's Hungarian assignment does, each target taking at most ceil(m / 2)
                              of the m pursuers: pursuers ordered by (distance to target 0 - distance to target 1),
                              ties to the lower index, the first c go to target 0, c the number of negative
                              differences clipped to [m - ceil(m / 2), ceil(m / 2)]. One target known: that one;
                              none: all 0.

evaders
    ``self_pos``, ``self_vel``, ``obstacles`` as above
    ``threats``    [K_t x 5]  the nearest pursuers or scouts within sensing range: dx, dy, vx, vy, valid
    ``teammates``  [K_m x 5]  the nearest other evaders within comm range: dx, dy, vx, vy, valid

Missing slots (fewer neighbours than slots) are all zero with valid = 0. With ``observability = "full"``
(what the paper trained with) every target is known with age 0 and ranges do not limit what is seen.

Action: a 2-D commanded velocity normalised to [-1, 1] per axis; the world multiplies it by the role's
``max_speed`` and limits its norm to ``max_speed``.
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from runtime.tomlmap import SECTION_NAMES, SpecError, from_mapping, load_toml

SPEC_FORMAT = 1
"""Bumped whenever the meaning of a field or the observation encoding changes without a field changing."""

ENGINES = ("onnxruntime", "compiled")
"""How ``runtime.policy.OnnxPolicy`` runs an actor: the names ``RunConfig``, the CLIs and fleet files accept."""

INT8_QMAX = 127
"""The int8 weight grid of the C export's ``--quant int8w`` (symmetric, one scale ``max|w| / INT8_QMAX`` per
output neuron); training's ``int8_robustness`` penalty injects noise of that step."""


class Role(enum.IntEnum):
    PURSUER = 0
    SCOUT = 1
    EVADER = 2

    @property
    def label(self) -> str:
        return self.name.lower()

    @classmethod
    def parse(cls, name: str) -> "Role":
        try:
            return cls[name.upper()]
        except KeyError:
            raise SpecError(f"unknown role {name!r}: use one of {[r.label for r in cls]}") from None


# --------------------------------------------------------------------------------------------------
# dataclasses


@dataclass(frozen=True)
class ArenaSpec:
    half_width: float = 3.0
    """Half the side of the square arena [m]; the arena is [-half_width, half_width]^2."""
    n_obstacles: int = 3
    """Circular obstacles placed at random in every episode."""
    obstacle_radius_min: float = 0.25
    """Smallest obstacle radius [m]."""
    obstacle_radius_max: float = 0.45
    """Largest obstacle radius [m]."""
    obstacle_clearance: float = 0.2
    """Free gap kept between obstacles, and between obstacles and walls, at placement [m]. Must exceed
    the largest agent diameter so that nobody can be wedged between two of them."""
    start_clearance: float = 0.05
    """Extra gap between a freshly placed agent and any obstacle or other agent [m]."""

    def __post_init__(self) -> None:
        _positive(self, "half_width")
        _nonnegative(self, "n_obstacles")
        _positive(self, "obstacle_radius_min")
        _positive(self, "obstacle_radius_max")
        _nonnegative(self, "obstacle_clearance")
        _nonnegative(self, "start_clearance")
        if self.obstacle_radius_max < self.obstacle_radius_min:
            raise SpecError(
                f"arena.obstacle_radius_max ({self.obstacle_radius_max}) is below arena.obstacle_radius_min "
                f"({self.obstacle_radius_min}): swap them or raise the maximum")
        # Obstacles with their clearance must fit comfortably (at most 40% of the usable square).
        inner = 2.0 * (self.half_width - self.obstacle_clearance)
        need = self.n_obstacles * math.pi * (self.obstacle_radius_max + self.obstacle_clearance) ** 2
        if self.n_obstacles and (inner <= 2 * self.obstacle_radius_max or need > 0.4 * inner * inner):
            raise SpecError(
                f"arena.n_obstacles: {self.n_obstacles} obstacles of radius up to {self.obstacle_radius_max} m "
                f"with clearance {self.obstacle_clearance} m do not fit in a {2 * self.half_width} m arena "
                f"(they would need {need:.2f} m^2 of {0.4 * inner * inner:.2f} m^2 allowed): use fewer or "
                f"smaller obstacles")


@dataclass(frozen=True)
class RoleSpec:
    radius: float
    """Body radius [m] used for collisions and contacts."""
    max_speed: float
    """Largest commanded speed [m/s]; an action of norm 1 asks for this speed."""
    max_accel: float
    """Acceleration limit [m/s^2] of the velocity response (a position-controlled drone)."""

    def __post_init__(self) -> None:
        _positive(self, "radius")
        _positive(self, "max_speed")
        _positive(self, "max_accel")


@dataclass(frozen=True)
class TeamSpec:
    n_pursuers: int = 5
    """Agents that chase the evaders."""
    n_scouts: int = 5
    """Pursuer-team agents rewarded for exploration (the paper's scouting pursuers)."""
    n_evaders: int = 2
    """Faster targets that learn to escape."""

    def __post_init__(self) -> None:
        _nonnegative(self, "n_pursuers")
        _nonnegative(self, "n_scouts")
        _positive(self, "n_evaders")
        if self.n_pursuers + self.n_scouts < 1:
            raise SpecError("team: the pursuer team is empty: set team.n_pursuers or team.n_scouts to 1 or more")

    @property
    def n_agents(self) -> int:
        return self.n_pursuers + self.n_scouts + self.n_evaders

    @property
    def n_team(self) -> int:
        """Pursuers plus scouts."""
        return self.n_pursuers + self.n_scouts

    def roles(self) -> tuple[Role, ...]:
        return ((Role.PURSUER,) * self.n_pursuers + (Role.SCOUT,) * self.n_scouts
                + (Role.EVADER,) * self.n_evaders)

    def indices(self, role: Role) -> range:
        if role is Role.PURSUER:
            return range(0, self.n_pursuers)
        if role is Role.SCOUT:
            return range(self.n_pursuers, self.n_team)
        return range(self.n_team, self.n_agents)

    def agent_ids(self) -> tuple[str, ...]:
        """Stable agent names, ``pursuer_0 ... scout_0 ... evader_0 ...``."""
        out: list[str] = []
        for role in Role:
            out += [f"{role.label}_{k}" for k in range(len(self.indices(role)))]
        return tuple(out)


@dataclass(frozen=True)
class SensingSpec:
    sensing_range: float = 0.5
    """Distance within which an agent detects another agent itself [m] (the paper's 0.5 m)."""
    comm_range: float = 2.0
    """Distance within which teammates exchange state and target sightings [m]."""
    target_memory: float = 3.0
    """A target sighting older than this is forgotten [s]."""
    observability: str = "full"
    """"full": every agent sees everything (what the paper trained with); "partial": targets are known
    only through own sensing or relayed by teammates in comm range (one hop per control period), with age."""
    n_obstacles_observed: int = 3
    """Obstacle slots in the observation (nearest first); at most arena.n_obstacles are used."""
    n_teammates_observed: int = 4
    """Teammate slots in the observation (nearest first)."""
    n_threats_observed: int = 4
    """Threat slots in an evader's observation (nearest pursuers or scouts)."""
    share_assignment: bool = field(default=False, metadata={"since": True})
    """Add the ``assigned`` field to the pursuer team's observation: the target this pursuer takes in the team's
    split, which every pursuer computes alike from the pursuers it hears and the targets it knows (the classical
    team's assignment, decentralized). Needs team.n_evaders <= 2. Off by default (the paper's observation); a spec
    with it off hashes as before the field existed."""

    def __post_init__(self) -> None:
        if not isinstance(self.share_assignment, bool):
            raise SpecError(f"sensing.share_assignment: must be true or false, got {self.share_assignment!r}")
        _positive(self, "sensing_range")
        _positive(self, "comm_range")
        _positive(self, "target_memory")
        if self.observability not in ("full", "partial"):
            raise SpecError(f"sensing.observability: {self.observability!r} is not one of 'full', 'partial'")
        _nonnegative(self, "n_obstacles_observed")
        _nonnegative(self, "n_teammates_observed")
        _nonnegative(self, "n_threats_observed")


@dataclass(frozen=True)
class TimingSpec:
    control_period: float = 0.1
    """Seconds between two actions (the policy's and the world's step) [s]."""
    episode_steps: int = 100
    """Control periods per episode."""

    def __post_init__(self) -> None:
        _positive(self, "control_period")
        _positive(self, "episode_steps")


@dataclass(frozen=True)
class AvoidanceSpec:
    """The learned actors' own avoidance layer (``runtime.avoidance``): every trained actor's action passes
    through it, in training, evaluation, the per-drone runtime and the C app, computed from the drone's own
    observation only (decentralized). It commands the velocity nearest the actor's among those that keep the
    speed toward every obstacle, wall and teammate within a braking barrier and that the drone can reach in one
    control period. Off by default (the paper's actors have none); a spec with it off hashes as before the table
    existed."""

    enabled: bool = False
    """Apply the layer to every trained actor of this spec (pursuers, scouts and evaders)."""
    braking: float = 1.5
    """Deceleration [m/s^2] the barrier plans with; below every role's max_accel so that a drone can follow
    the shrinking speed limit."""
    obstacle_margin: float = 0.04
    """Gap [m] to an obstacle's or a wall's surface where the allowed approach speed reaches zero."""
    teammate_margin: float = 0.1
    """Gap [m] between two teammates' bodies where the allowed approach speed reaches zero."""
    teammate_braking: float = field(default=0.0, metadata={"since": True})
    """Relative deceleration [m/s^2] the teammate barrier plans with: toward a teammate a drone's approach speed
    is at most half the barrier's limit at this deceleration (the teammate, flying the same layer, takes the other
    half), so each of two teammates closing in brakes at half of it. 0 (the default): ``braking``, the layer as it
    was before this field (each teammate braking at ``braking / 2``, twice as cautious as toward an obstacle);
    ``2 x braking`` asks of each teammate the deceleration an obstacle asks (configs/role_based.toml)."""
    teammate_credit: float = field(default=0.0, metadata={"since": True})
    """Share in [0, 1] of a teammate's own speed away from this drone (its velocity in the observation) that is
    added to this drone's approach budget toward it: a pursuer that follows a teammate in a chase line is then not
    braked by a leader flying away from it. The pair's closing speed at those velocities stays within the barrier's
    limit, as without it (this drone's approach less the teammate's retreat is at most its half of the limit, and a
    teammate that approaches earns it no credit). 0 (the default): the layer as it was before this field
    (results/README.md, twenty-third attempt)."""

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise SpecError(f"avoidance.enabled: must be true or false, got {self.enabled!r}")
        _positive(self, "braking")
        _nonnegative(self, "obstacle_margin")
        _nonnegative(self, "teammate_margin")
        _nonnegative(self, "teammate_braking")
        if not (math.isfinite(self.teammate_credit) and 0.0 <= self.teammate_credit <= 1.0):
            raise SpecError(f"avoidance.teammate_credit: must be a share in [0, 1] of the teammate's speed away (0: "
                            f"none), got {self.teammate_credit!r}")

    @property
    def mate_braking(self) -> float:
        """The teammate barrier's relative deceleration [m/s^2] in effect: ``teammate_braking``, or ``braking``
        where it is 0."""
        return self.teammate_braking or self.braking


def _default_pursuer() -> RoleSpec:
    return RoleSpec(radius=0.075, max_speed=1.0, max_accel=3.0)


def _default_scout() -> RoleSpec:
    return RoleSpec(radius=0.075, max_speed=1.0, max_accel=3.0)


def _default_evader() -> RoleSpec:
    return RoleSpec(radius=0.05, max_speed=1.3, max_accel=3.9)


@dataclass(frozen=True)
class SwarmSpec:
    """Everything a trained policy depends on. Frozen; build it from TOML with ``SwarmSpec.from_toml``."""

    arena: ArenaSpec = field(default_factory=ArenaSpec)
    pursuer: RoleSpec = field(default_factory=_default_pursuer)
    scout: RoleSpec = field(default_factory=_default_scout)
    evader: RoleSpec = field(default_factory=_default_evader)
    team: TeamSpec = field(default_factory=TeamSpec)
    sensing: SensingSpec = field(default_factory=SensingSpec)
    timing: TimingSpec = field(default_factory=TimingSpec)
    avoidance: AvoidanceSpec = field(default_factory=AvoidanceSpec)

    def __post_init__(self) -> None:
        if self.avoidance.enabled:
            slowest = min(self.role(r).max_accel for r in Role)
            if self.avoidance.braking >= slowest:
                raise SpecError(f"avoidance.braking ({self.avoidance.braking} m/s^2) must be below every role's "
                                f"max_accel (the smallest is {slowest} m/s^2) so that a drone can brake as planned: "
                                f"lower it")
            if self.avoidance.mate_braking / 2 >= slowest:
                raise SpecError(f"avoidance.teammate_braking ({self.avoidance.teammate_braking} m/s^2) must be below "
                                f"twice every role's max_accel (the smallest is {slowest} m/s^2): each of two "
                                f"teammates brakes at half of it; lower it")
        if self.sensing.share_assignment and self.team.n_evaders > 2:
            raise SpecError(f"sensing.share_assignment: the shared split is defined for at most 2 targets, the team has "
                            f"team.n_evaders = {self.team.n_evaders}: set share_assignment = false or use 1-2 evaders")
        biggest = max(self.pursuer.radius, self.scout.radius, self.evader.radius)
        if self.arena.n_obstacles and self.arena.obstacle_clearance <= 2 * biggest:
            raise SpecError(
                f"arena.obstacle_clearance ({self.arena.obstacle_clearance} m) must exceed the largest agent "
                f"diameter ({2 * biggest} m) so that no agent can be wedged between obstacles: raise it")
        # agents must be placeable: their discs plus clearance use at most 25% of the free area
        free = (2 * self.arena.half_width) ** 2 - self.arena.n_obstacles * math.pi * self.arena.obstacle_radius_max ** 2
        bodies = sum(math.pi * (self.role(r).radius * 2 + self.arena.start_clearance) ** 2 * len(self.team.indices(r))
                     for r in Role)
        if bodies > 0.25 * free:
            raise SpecError(f"team: {self.team.n_agents} agents do not fit in the arena: use fewer agents or a "
                            f"bigger arena.half_width")

    # -- lookups -------------------------------------------------------------------------------------
    def role(self, role: Role) -> RoleSpec:
        return (self.pursuer, self.scout, self.evader)[int(role)]

    @property
    def roles(self) -> tuple[Role, ...]:
        return self.team.roles()

    @property
    def n_agents(self) -> int:
        return self.team.n_agents

    def per_agent(self, attr: str) -> tuple[float, ...]:
        """``attr`` of ``RoleSpec`` for every agent in order (radius, max_speed, max_accel)."""
        return tuple(getattr(self.role(r), attr) for r in self.roles)

    def layout(self, role: Role) -> "ObsLayout":
        return _layout(self, Role(role))

    def obs_dim(self, role: Role) -> int:
        return self.layout(role).dim

    @property
    def max_obs_dim(self) -> int:
        return max(self.obs_dim(r) for r in set(self.roles))

    act_dim: int = field(default=2, init=False, repr=False)

    # -- (de)serialisation ---------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Every table as plain values; ``avoidance`` only when it differs from its default (off), and a field
        added later (``metadata={"since": True}``) only when it differs from its default, so that specs without the
        layer, or without such a field, serialise and hash exactly as before the table, or the field, existed."""
        return {f.name: _table_dict(getattr(self, f.name)) for f in dataclasses.fields(self)
                if f.init and not (f.name == "avoidance" and self.avoidance == AvoidanceSpec())}

    @property
    def hash(self) -> str:
        """12 hex digits over every field and the layout format; two specs with the same hash build the same
        observations and mean the same actions."""
        doc = {"format": SPEC_FORMAT, "spec": self.to_dict(),
               "layouts": {r.label: self.layout(r).describe() for r in Role}}
        blob = json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()
        return hashlib.sha256(blob).hexdigest()[:12]

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "spec") -> "SwarmSpec":
        return from_mapping(cls, data, where)

    @classmethod
    def from_toml(cls, path: str | Path, table: str | None = "spec") -> "SwarmSpec":
        data = load_toml(path)
        if table is not None:
            data = data.get(table, {})
        return cls.from_dict(data, where=table or "spec")


# --------------------------------------------------------------------------------------------------
# observation layout


@dataclass(frozen=True)
class ObsField:
    name: str
    rows: int
    """Slots (1 for a plain vector field)."""
    columns: tuple[str, ...]
    """Names of the values in one slot."""
    units: tuple[str, ...]
    low: tuple[float, ...]
    """Smallest value each column takes (used for random test inputs and the C export)."""
    high: tuple[float, ...]
    start: int = 0

    @property
    def size(self) -> int:
        return self.rows * len(self.columns)

    @property
    def slice(self) -> slice:
        return slice(self.start, self.start + self.size)


@dataclass(frozen=True)
class ObsLayout:
    role_group: str
    fields: tuple[ObsField, ...]

    @property
    def dim(self) -> int:
        return sum(f.size for f in self.fields)

    def __getitem__(self, name: str) -> ObsField:
        for f in self.fields:
            if f.name == name:
                return f
        raise KeyError(f"observation field {name!r} not in the {self.role_group} layout: "
                       f"{[f.name for f in self.fields]}")

    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    def describe(self) -> list[dict[str, Any]]:
        return [{"name": f.name, "start": f.start, "rows": f.rows, "columns": list(f.columns),
                 "units": list(f.units), "low": list(f.low), "high": list(f.high)} for f in self.fields]

    def bounds(self) -> tuple[list[float], list[float]]:
        """Per-index low and high of the whole observation vector."""
        lo: list[float] = []
        hi: list[float] = []
        for f in self.fields:
            lo += list(f.low) * f.rows
            hi += list(f.high) * f.rows
        return lo, hi

    @staticmethod
    def for_role(spec: SwarmSpec, role: Role) -> "ObsLayout":
        hw = spec.arena.half_width
        span = 2 * hw
        vmax = max(spec.pursuer.max_speed, spec.scout.max_speed, spec.evader.max_speed)
        rmax = spec.arena.obstacle_radius_max
        mem = spec.sensing.target_memory
        s = spec.sensing
        agent_cols = (("dx", "dy", "vx", "vy", "valid"), ("m", "m", "m/s", "m/s", "1"),
                      (-span, -span, -vmax, -vmax, 0.0), (span, span, vmax, vmax, 1.0))
        own_v = spec.role(role).max_speed
        raw = [("self_pos", 1, ("x", "y"), ("m", "m"), (-hw, -hw), (hw, hw)),
               ("self_vel", 1, ("vx", "vy"), ("m/s", "m/s"), (-own_v, -own_v), (own_v, own_v)),
               ("obstacles", min(s.n_obstacles_observed, spec.arena.n_obstacles), ("dx", "dy", "radius"),
                ("m", "m", "m"),
                (-span, -span, 0.0), (span, span, rmax))]
        if role is Role.EVADER:
            raw.append(("threats", s.n_threats_observed, *agent_cols))
            mates = min(s.n_teammates_observed, spec.team.n_evaders - 1)
        else:
            ev = spec.evader.max_speed
            raw.append(("targets", spec.team.n_evaders, ("dx", "dy", "vx", "vy", "age", "known"),
                        ("m", "m", "m/s", "m/s", "s", "1"),
                        (-span, -span, -ev, -ev, 0.0, 0.0), (span, span, ev, ev, mem, 1.0)))
            mates = min(s.n_teammates_observed, spec.team.n_team - 1)
        raw.append(("teammates", mates, *agent_cols))
        if role is not Role.EVADER and s.share_assignment:
            raw.append(("assigned", spec.team.n_evaders, ("mine",), ("1",), (0.0,), (1.0,)))
        fields: list[ObsField] = []
        start = 0
        for name, rows, cols, units, lo, hi in raw:
            f = ObsField(name, rows, cols, units, tuple(float(v) for v in lo), tuple(float(v) for v in hi), start)
            fields.append(f)
            start += f.size
        return ObsLayout("evader" if role is Role.EVADER else "pursuer_team", tuple(fields))


@functools.lru_cache(maxsize=64)
def _layout(spec: SwarmSpec, role: Role) -> ObsLayout:
    return ObsLayout.for_role(spec, role)


def _table_dict(table: Any) -> dict[str, Any]:
    """A spec table as plain values, without the fields added later (``metadata={"since": True}``) that hold their
    default: a spec that does not set them serialises, and hashes, as before they existed."""
    out = dataclasses.asdict(table)
    for f in dataclasses.fields(table):
        if f.metadata.get("since") and getattr(table, f.name) == f.default:
            del out[f.name]
    return out


def _positive(obj: Any, name: str) -> None:
    v = getattr(obj, name)
    if not v > 0:
        raise SpecError(f"{_section(obj)}.{name}: must be > 0, got {v!r}")


def _nonnegative(obj: Any, name: str) -> None:
    v = getattr(obj, name)
    if not v >= 0:
        raise SpecError(f"{_section(obj)}.{name}: must be >= 0, got {v!r}")


_SECTIONS = {"ArenaSpec": "arena", "RoleSpec": "role", "TeamSpec": "team", "SensingSpec": "sensing",
             "TimingSpec": "timing", "AvoidanceSpec": "avoidance"}
SECTION_NAMES.update(_SECTIONS)


def _section(obj: Any) -> str:
    return _SECTIONS.get(type(obj).__name__, type(obj).__name__)
