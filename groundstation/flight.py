"""Flight operations: preflight, staggered takeoff, the mission's setpoint stream, failsafes, landing.

``FlightSession`` is a context manager over open ``Link`` s (one per drone)::

    with FlightSession(links, teams, fence, FlightConfig(), actors=manifest_actors) as session:
        session.preflight(models_spec_hash=manifest.spec.hash, spec_hash=spec.hash)
        session.assign_roles()
        session.takeoff()
        session.start_mission()            # velocity commands from the per-drone runtimes now fly
        ...                                # session.set_command(drone_id, (vx, vy), t) from each runtime
    # every drone still in the air lands on exit, on an exception and on Ctrl-C

Setpoints. The per-drone runtimes hand in horizontal velocity commands (``set_command``); the session turns
them into setpoints at ``setpoint_rate``. A setpoint is computed when a drone's telemetry arrives and its
setpoint is due, from the measurement that just arrived (this keeps measurement-to-setpoint latency to the
processing time): horizontal command, through the separation filter (``separation.JointFilter``: every
drone's latest tracker position and velocity, solved jointly once per setpoint period on its own thread; the
receive threads read its cache), + an altitude-hold term, through the geofence (``safety.Geofence``), then
``link.send_velocity``. Nothing else sends setpoints. A holding drone's zero velocity needs no filter (zero is
the filter's own brake); to the filter it, and every drone not flying the mission, is an obstacle.

Failsafes, per drone, judged by the supervisor thread every ``1 / supervisor_rate`` s; the others fly on:

=========================  ==================================================================  ================
condition                  detection                                                           response
=========================  ==================================================================  ================
link loss                  telemetry silent for ``link_loss_timeout`` (cflib's UDP and radio   land commands are
                           drivers do not report a silent peer)                                repeated; roles
                                                                                               reassigned
stale or invalid position  the position source older than ``position_stale_after``, or the     hold (hover),
                           estimator's variance above ``max_position_variance``                land after
                                                                                               ``position_hold_time``
low battery                voltage below ``low_battery_v`` for ``low_battery_time``            land, reassign
agent fault                ``report_agent_fault`` (non-finite policy output, a crashed agent)  land, reassign
                           or no command for ``command_timeout``
outside the fence          ``safety.FenceGuard``: hold, then land after ``fence.hold_time``    land, reassign
=========================  ==================================================================  ================

A drone whose link is lost cannot be commanded: its own firmware levels out after 0.5 s without a setpoint
(horizontal control off: it coasts) and cuts the motors after 2 s (a Crazyflie drops from its flight height);
a Crazyflie link also arms the firmware's emergency-stop watchdog, which cuts the motors 1 s after the ground
station falls silent in any phase (``cflib_link``). The ground station keeps sending land commands in case
the link comes back.

Two things that would otherwise fake a failure: a ground station that itself did not run for a while (a
late supervisor tick) makes every link look silent, so silence is judged again only after a short grace;
and a takeoff or land command lost on the radio is repeated every 50 ms until the vehicle reports its
planner active (``Telemetry.planner_active``), because a Crazyflie whose priority was handed over
(notify-setpoint-stop) but whose planner got no command takes the idle planner's null setpoint: motors off.
A landing seen active is not re-sent once it has ended (the drone reports "flying" 2 s past touchdown).
"""
from __future__ import annotations

import collections
import enum
import json
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from groundstation import roles as roles_mod
from groundstation.link import FlightState, Link, LinkError, Telemetry
from groundstation.positioning import PositionTracker, battery_fraction
from groundstation.safety import FenceConfig, Geofence, GuardState, in_safe_set, limit_velocity
from groundstation.separation import JointFilter, Limits, SeparationConfig, Snapshot
from runtime.spec import Role, SpecError, from_mapping, load_toml

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FlightConfig:
    """Flight operations settings (TOML table ``[flight]``). Times in s, heights in m, voltages in V."""

    height: float = 0.6
    """Mission altitude [m] (clamped into the fence's altitude band)."""
    setpoint_rate: float = 20.0
    """Velocity setpoints per second and drone [Hz]; the firmware needs one at least every 0.5 s."""
    supervisor_rate: float = 100.0
    """How often failsafes are judged [Hz]."""
    fence_horizon: float = 0.6
    """Time [s] a velocity setpoint is assumed to be flown before the drone brakes, for the geofence's
    stopping-distance rule while the ground station keeps commanding. A drone whose link dies mid-command
    coasts instead; the geofence keeps that path free too (``fence.coast_time``)."""
    altitude_gain: float = 1.5
    """Vertical speed per metre of altitude error [1/s]."""
    max_vertical_speed: float = 0.3
    """[m/s]"""
    speed_scale: float = 1.0
    """Multiplier on the runtimes' velocity commands (< 1 flies the policies slower) [-]."""
    takeoff_duration: float = 2.0
    """[s] for the climb to ``height``."""
    takeoff_stagger: float = 0.2
    """Delay between two drones' takeoffs [s]."""
    takeoff_timeout: float = 6.0
    """A drone not within ``takeoff_tolerance`` of ``height`` this long after its takeoff is landed [s]."""
    takeoff_tolerance: float = 0.15
    """[m]"""
    land_speed: float = 0.4
    """Descent speed of a landing [m/s]."""
    land_timeout: float = 8.0
    """How long ``land_all`` waits for every reachable drone to report landed [s]."""
    land_retry: float = 0.5
    """Interval of repeated land commands to a drone that has not landed (or whose link is lost) [s]."""
    link_loss_timeout: float = 0.25
    """Telemetry silence that counts as link loss [s]."""
    position_stale_after: float = 0.2
    """A position older than this is stale [s]."""
    max_position_variance: float = 0.01
    """Largest per-axis variance of the position estimate that counts as valid [m^2]."""
    position_hold_time: float = 0.5
    """How long a drone with a stale or invalid position hovers before it is landed [s]."""
    min_takeoff_battery_v: float = 3.8
    """Preflight: resting battery voltage needed to take off [V]."""
    low_battery_v: float = 3.3
    """In flight: below this voltage (under load) for ``low_battery_time`` the drone lands [V]."""
    low_battery_time: float = 0.5
    """[s]"""
    command_timeout: float = 0.5
    """A drone flying an actor whose runtime sent no command for this long has an agent fault [s]."""
    record_rate: float = 10.0
    """Rows per second and drone written to the flight log [Hz]."""

    def __post_init__(self) -> None:
        for name in ("height", "setpoint_rate", "supervisor_rate", "fence_horizon", "altitude_gain",
                     "max_vertical_speed", "speed_scale", "takeoff_duration", "takeoff_timeout", "takeoff_tolerance",
                     "land_speed", "land_timeout", "land_retry", "link_loss_timeout", "position_stale_after",
                     "max_position_variance", "position_hold_time", "low_battery_time", "command_timeout",
                     "record_rate"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise SpecError(f"flight.{name}: must be a finite number > 0, got {v!r}")
        if not (math.isfinite(self.takeoff_stagger) and self.takeoff_stagger >= 0):
            raise SpecError(f"flight.takeoff_stagger: must be >= 0, got {self.takeoff_stagger!r}")
        if self.setpoint_rate < 2.5:
            raise SpecError(f"flight.setpoint_rate: {self.setpoint_rate} Hz leaves the firmware's 0.5 s setpoint "
                            f"watchdog no slack: use 10 Hz or more")
        if self.low_battery_v >= self.min_takeoff_battery_v:
            raise SpecError(f"flight.low_battery_v ({self.low_battery_v} V) must be below "
                            f"flight.min_takeoff_battery_v ({self.min_takeoff_battery_v} V)")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "flight") -> "FlightConfig":
        return from_mapping(cls, data, where)

    @classmethod
    def from_toml(cls, path: str | Path, table: str = "flight") -> "FlightConfig":
        return cls.from_dict(load_toml(path).get(table, {}), where=table)


class DroneStatus(str, enum.Enum):
    READY = "ready"
    """Connected, on the ground."""
    EXCLUDED = "excluded"
    """Failed preflight; never takes off."""
    TAKING_OFF = "taking_off"
    FLYING = "flying"
    HOLDING = "holding"
    """In the air, hovering because its position is stale or invalid."""
    LANDING = "landing"
    LANDED = "landed"
    LOST = "lost"
    """Link lost in the air; land commands are repeated."""
    STOPPED = "stopped"
    """Emergency-stopped."""


AIRBORNE = (DroneStatus.TAKING_OFF, DroneStatus.FLYING, DroneStatus.HOLDING)
STALL_GAP = 0.1
"""A supervisor tick later than this after the previous one means the ground station stalled [s]."""
STALL_GRACE = 0.05
"""After a stall, telemetry silence is judged again only this much later [s], once the receive threads have
delivered what queued up meanwhile."""
LAND_CONFIRM_RETRY = 0.05
"""Interval of repeated land (and takeoff) commands until the vehicle's planner reports it took one [s]."""


class PreflightError(RuntimeError):
    """Preflight failed; ``failures`` maps drone id (or ``"models"``) to the reason."""

    def __init__(self, failures: Mapping[str, str]) -> None:
        self.failures = dict(failures)
        lines = "\n".join(f"  - {k}: {v}" for k, v in self.failures.items())
        super().__init__(f"preflight failed for {len(self.failures)} item(s):\n{lines}")


@dataclass
class _Drone:
    id: str
    link: Link
    team: str
    status: DroneStatus = DroneStatus.READY
    reason: str = ""
    lock: threading.Lock = field(default_factory=threading.Lock)
    command: np.ndarray = field(default_factory=lambda: np.zeros(2))
    command_t: float = -math.inf
    actor_since: float = -math.inf
    setpoint: np.ndarray | None = None
    setpoint_t: float = -math.inf
    status_since: float = 0.0
    takeoff_t: float = math.inf
    invalid_since: float | None = None
    low_battery_since: float | None = None
    land_sent_t: float = -math.inf
    land_acked: bool = False
    """The vehicle's planner was seen flying the latest land command (a finished landing is not re-sent)."""
    fault: str | None = None
    retire_actor: bool = False
    fence_breach: bool = False


@dataclass(frozen=True)
class FlightEvent:
    """One failsafe or operations event (also written to the flight log)."""

    t: float
    """[s, time.monotonic()]"""
    drone: str | None
    kind: str
    detail: str = ""
    data: Mapping[str, Any] = field(default_factory=dict)


class FlightSession:
    """Flight operations over open links. See the module docstring.

    ``links``: drone id -> open ``Link``. ``teams``: drone id -> ``"pursuer"`` (flies pursuer and scout
    actors) or ``"evader"``. ``actors``: the model manifest's actors (``roles.parse_actors`` input).
    ``record``: called with one dict per flight-log row and per event (``JsonlRecorder`` writes them).
    The session owns neither the links nor the simulator: close them after the session has exited.
    """

    def __init__(self, links: Mapping[str, Link], teams: Mapping[str, str], fence: FenceConfig,
                 config: FlightConfig = FlightConfig(), actors: Iterable[Any] = (),
                 tracker: PositionTracker | None = None,
                 record: Callable[[dict], None] | None = None, latency_probe: bool = False,
                 separation: SeparationConfig = SeparationConfig()) -> None:
        if not links:
            raise ValueError("FlightSession needs at least one link")
        if latency_probe and not all(link.uri.startswith("udp://") for link in links.values()):
            raise ValueError("latency_probe puts a timestamp in the yaw rate: simulated drones (udp://) only")
        self.latency_probe = latency_probe
        """Simulator benchmark: every velocity setpoint's yaw rate [rad/s] carries the vehicle timestamp (mod
        2^16 ms) of the measurement it answers, so the simulator can time measurement-to-setpoint at the
        drone (``SimSwarm(latency_probe=True)``). A real drone would spin: refused for other than udp://."""
        missing = sorted(set(links) - set(teams))
        if missing:
            raise ValueError(f"drone {missing[0]}: no team given: pass teams[{missing[0]!r}] = 'pursuer' or 'evader'")
        self.config = config
        self.fence = fence
        self.geofence = Geofence(fence)
        self.tracker = tracker or PositionTracker(stale_after=config.position_stale_after)
        self.actors = roles_mod.parse_actors(actors)
        self.drones = {d: _Drone(d, link, teams[d]) for d, link in links.items()}
        self.assignment = roles_mod.Assignment(self.actors, {})
        self.role_changes: list[roles_mod.RoleChange] = []
        self.events: list[FlightEvent] = []
        self.latencies: collections.deque[float] = collections.deque(maxlen=200_000)
        """Measurement-to-setpoint delays [s]: telemetry arrival to the setpoint handed to the link."""
        self.role_listeners: list[Callable[[roles_mod.Assignment], None]] = []
        self.height = self.geofence.clamp_height(config.height)
        self._record = record
        self._retired: set[str] = set()
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._mission = False
        self._callbacks: dict[str, Callable[[Telemetry], None]] = {}
        self._period = 1.0 / config.setpoint_rate
        self.separation_config = separation
        self.separation: JointFilter | None = None
        """The separation filter; None only with ``separation.enabled = False`` (comparisons)."""
        if separation.enabled:
            # latency: the cached solution's age (one period) + the measurement's age and the link (one more)
            limits = Limits(separation.min_distance, self._period, fence.max_decel, fence.max_speed,
                            latency=2.0 * self._period)
            self.separation = JointFilter(limits, self._separation_snapshot, interval=self._period)
        self._t0 = time.monotonic()
        self._next_record = 0.0
        self._last_tick = time.monotonic()
        self._grace_until = 0.0
        self.stalls = 0
        """Times the supervisor found that the ground station itself had not run for ``STALL_GAP``."""

    # ---- context manager ---------------------------------------------------------------------------

    def __enter__(self) -> "FlightSession":
        for d in self.drones.values():
            self.tracker.attach(d.id, d.link)  # registered first: the setpoint callback reads the tracker
            cb = self._make_callback(d)
            d.link.add_telemetry_callback(cb)
            self._callbacks[d.id] = cb
        self._supervisor = threading.Thread(target=self._supervise, name="FlightSupervisor", daemon=True)
        self._supervisor.start()
        if self.separation is not None:
            self.separation.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self._event(None, "abort", f"{exc_type.__name__}: {exc}" if str(exc) else exc_type.__name__)
        try:
            self.land_all()
        except KeyboardInterrupt:
            log.warning("interrupted while landing: emergency stop")
            self.emergency_stop("interrupted during landing")
        finally:
            self._stop.set()
            if self._supervisor is not None:
                self._supervisor.join(timeout=2.0)
            if self.separation is not None:
                self.separation.stop()
            for d in self.drones.values():
                cb = self._callbacks.pop(d.id, None)
                if cb is not None:
                    try:
                        d.link.remove_telemetry_callback(cb)
                    except ValueError:
                        log.debug("%s: setpoint callback was already removed", d.id)
                self.tracker.detach(d.id)

    # ---- queries -----------------------------------------------------------------------------------

    def status(self, drone_id: str) -> DroneStatus:
        return self.drones[drone_id].status

    def statuses(self) -> dict[str, DroneStatus]:
        return {d: x.status for d, x in self.drones.items()}

    def time(self) -> float:
        """Seconds since the session was created."""
        return time.monotonic() - self._t0

    def events_of(self, kind: str, drone_id: str | None = None) -> list[FlightEvent]:
        return [e for e in self.events if e.kind == kind and (drone_id is None or e.drone == drone_id)]

    def actor_of(self, drone_id: str) -> str | None:
        return self.assignment.by_drone.get(drone_id)

    def is_flying(self, drone_id: str) -> bool:
        """In the mission: flying with a valid position (not taking off, holding, landing or lost)."""
        return self.drones[drone_id].status is DroneStatus.FLYING

    def flying(self) -> list[str]:
        return [d for d, x in self.drones.items() if x.status in AIRBORNE]

    def geofence_violations(self) -> int:
        return sum(self.geofence.stats(d).violations for d in self.drones)

    def snapshot(self, events_since: int = 0, max_events: int = 100) -> dict[str, Any]:
        """The session's state for observers (the live view): JSON-ready values. No drone's lock is taken, so an
        observer never holds up a setpoint: every value read here is one attribute that its writer replaces
        whole (statuses, setpoints, telemetry samples, the assignment), never mutates in place. ``events``: the
        events from index ``events_since`` on (each with its index ``i``), the latest ``max_events`` of them."""
        now = time.monotonic()
        assignment = self.assignment
        rnd = lambda v, n=4: None if v is None else [round(float(c), n) for c in v]  # noqa: E731
        drones = []
        for d in list(self.drones.values()):
            tel = d.link.telemetry()
            role = assignment.role_of_drone(d.id)
            sp, sp_t, cmd_t = d.setpoint, d.setpoint_t, max(d.command_t, d.actor_since)
            drones.append({
                "id": d.id, "team": d.team, "role": role.label if role is not None else None,
                "actor": assignment.by_drone.get(d.id), "status": d.status.value, "reason": d.reason,
                "position": rnd(tel.position) if tel is not None else None,
                "velocity": rnd(tel.velocity) if tel is not None else None,
                "battery": round(float(tel.battery), 3) if tel is not None else None,
                "link_quality": round(float(tel.link_quality), 3) if tel is not None else None,
                "position_variance": (float(f"{max(tel.position_variance):.3g}")
                                      if tel is not None and tel.position_variance else None),
                "setpoint": rnd(sp), "setpoint_age": round(now - sp_t, 3) if math.isfinite(sp_t) else None,
                "command_age": round(now - cmd_t, 3) if math.isfinite(cmd_t) else None,
                "telemetry_age": round(min(d.link.telemetry_age(now), 999.0), 3),
            })
        n = len(self.events)
        first = max(events_since, n - max_events, 0)
        events = [{"i": i, "t": round(e.t - self._t0, 3), "drone": e.drone, "kind": e.kind, "detail": e.detail}
                  for i, e in zip(range(first, n), self.events[first:n])]
        return {"t": round(now - self._t0, 3), "mission": self._mission, "drones": drones, "events": events,
                "n_events": n}

    # ---- preflight and roles -----------------------------------------------------------------------

    def preflight(self, spec_hash: str | None = None, models_spec_hash: str | None = None,
                  require_all: bool = True, timeout: float = 2.0) -> dict[str, str]:
        """Check every drone: link up with fresh telemetry, battery >= ``min_takeoff_battery_v``, a valid
        position (fresh, small variance) on the ground inside the fence's safe area, and that the models were
        exported for this spec. Returns drone id -> failure. A drone that fails is EXCLUDED; with
        ``require_all`` (or a models mismatch) ``PreflightError`` is raised instead."""
        cfg = self.config
        failures: dict[str, str] = {}
        if spec_hash is not None and models_spec_hash is not None and spec_hash != models_spec_hash:
            failures["models"] = (f"the models were exported for spec {models_spec_hash}, the ground station "
                                  f"encodes observations for spec {spec_hash}: export models trained on this spec")
        deadline = time.monotonic() + timeout
        for d in self.drones.values():
            problem = None
            while True:
                problem = self._preflight_problem(d, cfg)
                if problem is None or time.monotonic() > deadline:
                    break
                time.sleep(0.05)  # telemetry may still be arriving (battery comes in the slow log block)
            if problem is not None:
                failures[d.id] = problem
        for did, why in failures.items():
            self._event(did if did in self.drones else None, "preflight_failed", why)
        if failures and (require_all or "models" in failures):
            raise PreflightError(failures)
        for did in failures:
            self._set_status(self.drones[did], DroneStatus.EXCLUDED, failures[did])
        self._event(None, "preflight_ok", f"{len(self.drones) - len(failures)} of {len(self.drones)} drones ready")
        return failures

    def _preflight_problem(self, d: _Drone, cfg: FlightConfig) -> str | None:
        tel = d.link.telemetry()
        if tel is None or d.link.link_lost:
            return f"link down: no telemetry for {d.link.telemetry_age():.2f} s"
        ready = (FlightState.LANDED, FlightState.DISARMED) if d.link.arms_on_takeoff else (FlightState.LANDED,)
        if tel.flight_state not in ready:
            return (f"flight state {tel.flight_state.value}, expected "
                    + " or ".join(r.value for r in ready) + " (on the ground)")
        if not tel.battery >= cfg.min_takeoff_battery_v:
            return f"battery {tel.battery:.2f} V below {cfg.min_takeoff_battery_v:.2f} V: charge or swap it"
        pos = self.tracker.position(d.id)
        if pos is None:
            return "position stale or unknown"
        var = tel.position_variance
        if var is not None and not max(var) <= cfg.max_position_variance:
            return (f"position estimate not converged (variance {max(var):.3g} m^2 > "
                    f"{cfg.max_position_variance:g}): check the positioning system")
        if not in_safe_set(self.fence, (pos[0], pos[1], self.fence.z_band[0])):
            return (f"on the ground at ({pos[0]:.2f}, {pos[1]:.2f}) m, outside the fence's safe area: move it "
                    f"inside the fence and away from keep-out zones")
        return None

    def assign_roles(self) -> roles_mod.Assignment:
        """Initial role assignment over the drones that passed preflight (by battery and distance)."""
        with self._lock:
            infos = self._drone_infos(for_takeoff=True)
            self.assignment = roles_mod.assign_roles(self.actors, infos)
            now = time.monotonic()
            for d in self.drones.values():
                d.actor_since = now
            self._event(None, "roles_assigned", "", {"by_drone": self.assignment.by_drone})
        self._notify_roles()
        return self.assignment

    def _drone_infos(self, for_takeoff: bool = False) -> list[roles_mod.DroneInfo]:
        out = []
        ok = (DroneStatus.READY,) if for_takeoff else (DroneStatus.FLYING, DroneStatus.HOLDING,
                                                         DroneStatus.TAKING_OFF)
        for d in self.drones.values():
            s = self.tracker.get(d.id)
            tel = d.link.telemetry()
            out.append(roles_mod.DroneInfo(
                d.id, s.position if s is not None else (0.0, 0.0, 0.0),
                battery_fraction(tel.battery) if tel is not None else 0.0,
                available=d.status in ok and d.fault is None, team=d.team))
        return out

    def _reassign(self, reason: str) -> None:
        with self._lock:
            actors = tuple(a for a in self.actors if a.id not in self._retired)
            current = roles_mod.Assignment(actors, {a: d for a, d in self.assignment.by_actor.items()
                                                    if a not in self._retired})
            role = {a.id: a.role for a in actors}
            n_evaders = sum(1 for a, d in current.by_actor.items()
                            if role[a] is Role.EVADER and self.drones[d].status in AIRBORNE)
            new, changes = roles_mod.reassign(current, self._drone_infos(), n_evaders,
                                              low_battery=battery_fraction(self.config.low_battery_v))
            now = time.monotonic()
            before = self.assignment.by_drone
            for did, actor in new.by_drone.items():
                if before.get(did) != actor:
                    self.drones[did].actor_since = now
            self.assignment = new
            self.role_changes += changes
            self._event(None, "roles_reassigned", reason,
                        {"changes": [c.describe() for c in changes], "by_drone": new.by_drone})
        self._notify_roles()

    def _notify_roles(self) -> None:
        for listener in list(self.role_listeners):
            try:
                listener(self.assignment)
            except Exception:  # a listener must not stop the failsafes
                log.exception("role listener %r failed", listener)

    # ---- takeoff, mission, landing -----------------------------------------------------------------

    def takeoff(self, wait: bool = True) -> list[str]:
        """Staggered takeoff of every READY drone to ``height``; with ``wait`` blocks until each is up (or
        was landed for missing ``takeoff_timeout``). Returns the drones that are flying."""
        cfg = self.config
        ready = [d for d in self.drones.values() if d.status is DroneStatus.READY]
        for k, d in enumerate(ready):
            if k:
                time.sleep(cfg.takeoff_stagger)
            with d.lock:
                if d.status is not DroneStatus.READY:
                    continue
                try:
                    d.link.takeoff(self.height, cfg.takeoff_duration)
                except LinkError as exc:
                    self._set_status(d, DroneStatus.EXCLUDED, f"takeoff failed: {exc.problem}")
                    continue
                d.takeoff_t = d.land_sent_t = time.monotonic()
                self._set_status(d, DroneStatus.TAKING_OFF, f"to {self.height:.2f} m")
        if wait:
            deadline = time.monotonic() + cfg.takeoff_duration + cfg.takeoff_timeout
            while time.monotonic() < deadline and any(d.status is DroneStatus.TAKING_OFF for d in ready):
                time.sleep(0.02)
        return self.flying()

    def start_mission(self) -> None:
        """From now on flying drones follow the runtimes' commands (until then they hover)."""
        now = time.monotonic()
        with self._lock:
            for d in self.drones.values():
                d.actor_since = max(d.actor_since, now)
            self._mission = True
        self._event(None, "mission_start", f"{len(self.flying())} drones flying")

    def stop_mission(self) -> None:
        with self._lock:
            self._mission = False
        self._event(None, "mission_end")

    def set_command(self, drone_id: str, velocity: Sequence[float] | np.ndarray, t: float | None = None) -> None:
        """The latest horizontal velocity command [m/s, world frame] of a drone's runtime (the command sink).
        Non-finite commands are an agent fault."""
        d = self.drones[drone_id]
        v = np.asarray(velocity, dtype=float).reshape(-1)[:2]
        if v.shape != (2,) or not np.all(np.isfinite(v)):
            self.report_agent_fault(drone_id, f"non-finite velocity command {velocity!r}")
            return
        d.command = v * self.config.speed_scale
        d.command_t = time.monotonic() if t is None else t

    def report_agent_fault(self, drone_id: str, reason: str, retire_actor: bool = False) -> None:
        """A drone's runtime failed (``retire_actor``: the fault is in the actor's model itself, so no other
        drone may take that actor over). The supervisor lands the drone and reassigns roles."""
        d = self.drones[drone_id]
        if d.fault is None:
            d.retire_actor = retire_actor
            d.fault = reason

    def land(self, drone_id: str, reason: str = "commanded") -> None:
        """Land one drone (it leaves the mission; roles are reassigned)."""
        d = self.drones[drone_id]
        if d.status in AIRBORNE:
            self._begin_landing(d, reason)
            self._reassign(f"{drone_id} landing: {reason}")

    def land_all(self, reason: str = "end of flight", wait: bool = True) -> dict[str, DroneStatus]:
        """Land every drone in the air; with ``wait`` block until each reports landed (lost drones cannot)
        or ``land_timeout`` passes. Returns the final statuses."""
        self._mission = False
        for d in self.drones.values():
            if d.status in AIRBORNE:
                self._begin_landing(d, reason)
        if wait:
            deadline = time.monotonic() + self.config.land_timeout
            while time.monotonic() < deadline:
                self._check_landings(time.monotonic())
                if not any(d.status is DroneStatus.LANDING for d in self.drones.values()):
                    break
                time.sleep(0.05)
        return self.statuses()

    def emergency_stop(self, reason: str = "operator") -> None:
        """Cut every drone's motors now (they fall and stay locked until rebooted)."""
        self._mission = False
        for d in self.drones.values():
            with d.lock:
                try:
                    d.link.emergency_stop()
                except LinkError as exc:
                    log.error("%s: emergency stop not sent: %s", d.id, exc)
                if d.status not in (DroneStatus.EXCLUDED,):
                    self._set_status(d, DroneStatus.STOPPED, reason)
        self._event(None, "emergency_stop", reason)

    # ---- setpoints (each link's receive thread) ----------------------------------------------------

    def _make_callback(self, d: _Drone) -> Callable[[Telemetry], None]:
        fence, cfg = self.fence, self.config
        due = self._period - 0.004  # telemetry arrives every few ms: send on the first sample once due

        def on_telemetry(sample: Telemetry) -> None:
            if d.status not in (DroneStatus.FLYING, DroneStatus.HOLDING):
                return
            now = time.monotonic()
            if now - d.setpoint_t < due:
                return
            with d.lock:
                if d.status is DroneStatus.FLYING:
                    pos = self.tracker.position(d.id)
                    if pos is None:
                        return  # the supervisor moves it to HOLDING
                    v = np.zeros(3)
                    v[:2] = self._desired(d)
                    if self.separation is not None:
                        v[:2] = self.separation.command(d.id, now)
                    v[2] = min(max(cfg.altitude_gain * (self.height - pos[2]), -cfg.max_vertical_speed),
                               cfg.max_vertical_speed)
                    out = self.geofence.filter_velocity(d.id, pos, v, cfg.fence_horizon)
                    if out.state is GuardState.LAND:
                        d.fence_breach = True  # the supervisor lands it
                    value = out.value  # zero (a hover) while the guard holds or lands
                elif d.status is DroneStatus.HOLDING:
                    # position unknown: hover in place on the onboard estimate (zero passes any velocity limit)
                    value = limit_velocity(fence, self._last_position(d), np.zeros(3), cfg.fence_horizon)
                else:
                    return
                try:
                    tag = float(sample.vehicle_time_ms & 0xFFFF) if self.latency_probe and \
                        sample.vehicle_time_ms is not None else 0.0
                    d.link.send_velocity(float(value[0]), float(value[1]), float(value[2]), tag)
                except LinkError:
                    return
                sent = time.monotonic()
                d.setpoint, d.setpoint_t = value, sent
                self.latencies.append(sent - sample.t)

        return on_telemetry

    def _desired(self, d: _Drone) -> np.ndarray:
        """The horizontal command [m/s] the drone would fly without the separation filter."""
        if self._mission and self.assignment.by_drone.get(d.id) is not None:
            return d.command
        return np.zeros(2)

    def _separation_snapshot(self) -> Snapshot:
        """Every drone the tracker can place, for the separation filter: those flying the mission with a fresh
        position obey it; the others (taking off, holding, landing, lost, on the ground) are obstacles at their
        last known position and velocity. Positions are carried forward by velocity x age (up to
        ``position_stale_after``): telemetry that queued behind a stalled ground station is that much old."""
        ids, pos, vel, want, ctrl, prev = [], [], [], [], [], []
        now = time.monotonic()
        for d in self.drones.values():
            s = self.tracker.get(d.id)
            if s is None:
                continue
            controlled = d.status is DroneStatus.FLYING and self.tracker.position(d.id) is not None
            sp = d.setpoint
            in_flight = sp is not None and now - d.setpoint_t <= 2 * self._period
            age = min(max(now - s.t, 0.0), self.config.position_stale_after)
            ids.append(d.id)
            pos.append(np.add(s.position[:2], np.multiply(s.velocity[:2], age)))
            vel.append(s.velocity[:2])
            want.append(self._desired(d) if controlled else np.zeros(2))
            ctrl.append(controlled)
            prev.append(sp[:2] if in_flight and controlled else s.velocity[:2])
        as2 = lambda rows: np.array(rows, dtype=float).reshape(-1, 2)  # noqa: E731
        return Snapshot(ids, as2(pos), as2(vel), as2(want), np.array(ctrl, dtype=bool), as2(prev))

    def separation_stats(self) -> dict[str, Any]:
        """The filter's counters (solves, methods, braked setpoints); ``{"enabled": False}`` without it."""
        if self.separation is None:
            return {"enabled": False}
        return {"enabled": True, "min_distance": self.separation_config.min_distance, **self.separation.stats()}

    def _last_position(self, d: _Drone) -> np.ndarray:
        s = self.tracker.get(d.id)
        return np.array(s.position) if s is not None else self.fence.home

    # ---- the supervisor ----------------------------------------------------------------------------

    def _supervise(self) -> None:
        period = 1.0 / self.config.supervisor_rate
        next_t = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                self._tick(now)
            except Exception:  # the failsafes must keep running whatever one check raised
                log.exception("flight supervisor tick failed")
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t = time.monotonic()
                delay = 0.0
            self._stop.wait(delay)

    def _tick(self, now: float) -> None:
        cfg = self.config
        reassign: list[str] = []
        gap = now - self._last_tick
        self._last_tick = now
        if gap > STALL_GAP:
            # The ground station itself did not run (CPU starvation, a paused process): every link looks
            # silent for that long. Give the receive threads time to deliver what queued up before telemetry
            # silence is judged again, or one stall would "lose" the whole swarm.
            self._grace_until = now + STALL_GRACE
            self.stalls += 1
            self._event(None, "ground_station_stall", f"supervisor did not run for {gap * 1e3:.0f} ms",
                        {"gap_s": gap})
        judge_silence = now >= self._grace_until
        for d in self.drones.values():
            st = d.status
            if st in AIRBORNE:
                why = self._failsafe(d, now, judge_silence)
                if why is not None:
                    reassign.append(f"{d.id}: {why}")
            elif st is DroneStatus.LOST and now - d.land_sent_t >= cfg.land_retry:
                self._send_land(d, now)
                if not d.link.link_lost:  # it answers again: land it properly
                    self._set_status(d, DroneStatus.LANDING, "link back")
        self._check_landings(now)
        if reassign and self.actors:
            self._reassign("; ".join(reassign))
        if now >= self._next_record:
            self._next_record = now + 1.0 / cfg.record_rate
            self._write_rows(now)

    def _failsafe(self, d: _Drone, now: float, judge_silence: bool = True) -> str | None:
        """Judge one airborne drone; returns why it left the mission, or None. ``judge_silence`` False: the
        ground station has just stalled, so telemetry silence and stale positions are not judged yet."""
        cfg = self.config
        link = d.link
        silence = link.telemetry_age(now)
        if judge_silence and (link.link_lost or silence > cfg.link_loss_timeout):
            with d.lock:
                self._set_status(d, DroneStatus.LOST, f"no telemetry for {silence * 1e3:.0f} ms")
            self._event(d.id, "link_lost", f"telemetry silent for {silence * 1e3:.0f} ms",
                        {"silence_s": silence})
            self._send_land(d, now)
            return "link lost"
        tel = link.telemetry()
        if d.status is DroneStatus.TAKING_OFF:
            s = self.tracker.get(d.id)
            if s is not None and abs(s.position[2] - self.height) <= cfg.takeoff_tolerance:
                with d.lock:
                    self._set_status(d, DroneStatus.FLYING, "at mission height")
            elif now - d.takeoff_t > cfg.takeoff_duration + cfg.takeoff_timeout:
                self._begin_landing(d, "did not reach mission height")
                return "takeoff failed"
            elif tel is not None and tel.flight_state is FlightState.LANDED and not tel.planner_active \
                    and tel.t > d.land_sent_t and now - d.land_sent_t >= 4 * LAND_CONFIRM_RETRY:
                # the takeoff command was lost (radio links drop packets): ask again; a drone already
                # climbing reports FLYING and is left alone
                with d.lock:
                    d.land_sent_t = now
                    try:
                        d.link.takeoff(self.height, cfg.takeoff_duration)
                    except LinkError as exc:
                        log.warning("%s: takeoff command not sent: %s", d.id, exc)
            return None
        if tel is not None and tel.battery < cfg.low_battery_v:
            if d.low_battery_since is None:
                d.low_battery_since = now
            elif now - d.low_battery_since >= cfg.low_battery_time:
                self._event(d.id, "low_battery", f"{tel.battery:.2f} V < {cfg.low_battery_v:.2f} V",
                            {"battery_v": tel.battery})
                self._begin_landing(d, f"low battery {tel.battery:.2f} V")
                return "low battery"
        else:
            d.low_battery_since = None
        if d.fault is None and self._mission and self.assignment.by_drone.get(d.id) is not None:
            last = max(d.command_t, d.actor_since)
            if now - last > cfg.command_timeout:
                d.fault = f"no command from its runtime for {now - last:.2f} s"
        if d.fence_breach:
            self._event(d.id, "fence_breach", "measured outside the fence for longer than fence.hold_time")
            self._begin_landing(d, "outside the fence")
            return "outside the fence"
        if d.fault is not None:
            if d.retire_actor:
                actor = self.assignment.by_drone.get(d.id)
                if actor is not None:
                    self._retired.add(actor)
            self._event(d.id, "agent_fault", d.fault, {"actor": self.assignment.by_drone.get(d.id),
                                                       "actor_retired": d.retire_actor})
            self._begin_landing(d, f"agent fault: {d.fault}")
            return "agent fault"
        pos = self.tracker.position(d.id)
        var = tel.position_variance if tel is not None else None
        if pos is None and not judge_silence:
            return None
        invalid = pos is None or (var is not None and not max(var) <= cfg.max_position_variance)
        if invalid:
            if d.invalid_since is None:
                d.invalid_since = now
                why = "stale" if pos is None else f"variance {max(var):.3g} m^2"
                with d.lock:
                    self._set_status(d, DroneStatus.HOLDING, f"position {why}")
                self._event(d.id, "position_invalid", why, {"age_s": self.tracker.age(d.id)})
            elif now - d.invalid_since >= cfg.position_hold_time:
                self._begin_landing(d, "position stale or invalid")
                return "position lost"
        elif d.invalid_since is not None:
            d.invalid_since = None
            with d.lock:
                self._set_status(d, DroneStatus.FLYING, "position valid again")
        return None

    def _begin_landing(self, d: _Drone, reason: str) -> None:
        with d.lock:
            if d.status in (DroneStatus.LANDING, DroneStatus.LANDED, DroneStatus.STOPPED, DroneStatus.EXCLUDED):
                return
            if d.status is DroneStatus.READY:
                self._set_status(d, DroneStatus.LANDED, reason)
                return
            lost = d.status is DroneStatus.LOST
            self._set_status(d, DroneStatus.LOST if lost else DroneStatus.LANDING, reason)
            self._send_land(d, time.monotonic())

    def _send_land(self, d: _Drone, now: float) -> None:
        s = self.tracker.get(d.id)
        z = s.position[2] if s is not None and math.isfinite(s.position[2]) else self.height
        d.land_sent_t, d.land_acked = now, False
        try:
            d.link.land(max(z, 0.1) / self.config.land_speed + 0.2)
        except LinkError as exc:
            log.warning("%s: land command not sent: %s", d.id, exc)

    def _check_landings(self, now: float) -> None:
        """Follow every landing to the ground. A land command can be lost on the radio: until the vehicle
        reports its planner active (or, for links that do not report it, until the landing should have
        ended) the command is repeated, every ``LAND_CONFIRM_RETRY`` s at first; a Crazyflie that took the
        hand-over but not the land cuts its motors at once."""
        for d in self.drones.values():
            if d.status is not DroneStatus.LANDING:
                continue
            tel = d.link.telemetry()
            # DISARMED: ArduPilot and PX4 disarm by themselves once down
            if tel is not None and not d.link.link_lost and tel.flight_state in (FlightState.LANDED,
                                                                                 FlightState.LOCKED,
                                                                                 FlightState.DISARMED):
                with d.lock:
                    self._set_status(d, DroneStatus.LANDED, f"on the ground at z = {tel.position[2]:.2f} m")
                if tel.flight_state is FlightState.LOCKED:
                    self._event(d.id, "dropped", "the firmware cut the motors (locked) instead of landing")
            elif d.link.link_lost:
                with d.lock:
                    self._set_status(d, DroneStatus.LOST, "link lost while landing")
            elif tel is not None and tel.planner_active and tel.t > d.land_sent_t:
                # Taken. Not again once the landing has ended: a Crazyflie reports "flying" for 2 s after
                # touchdown (supervisor.c), and a land sent to its idle planner would spin the motors again.
                d.land_acked = True
            elif d.land_acked:
                continue
            elif tel is not None and tel.planner_active is False and tel.t > d.land_sent_t \
                    and now - d.land_sent_t >= LAND_CONFIRM_RETRY:
                self._send_land(d, now)
            elif now - d.land_sent_t > max(self.config.land_retry, self.height / self.config.land_speed + 1.0):
                self._send_land(d, now)

    def _set_status(self, d: _Drone, status: DroneStatus, reason: str = "") -> None:
        if d.status is status:
            return
        old = d.status
        d.status, d.reason, d.status_since = status, reason, time.monotonic()
        self._event(d.id, "status", f"{old.value} -> {status.value}" + (f" ({reason})" if reason else ""),
                    {"from": old.value, "to": status.value})

    # ---- records -----------------------------------------------------------------------------------

    def _event(self, drone: str | None, kind: str, detail: str = "", data: Mapping[str, Any] | None = None) -> None:
        ev = FlightEvent(time.monotonic(), drone, kind, detail, dict(data or {}))
        self.events.append(ev)
        level = logging.INFO if kind in ("status", "roles_assigned", "preflight_ok", "mission_start",
                                         "mission_end") else logging.WARNING
        log.log(level, "%s%s: %s", f"{drone} " if drone else "", kind, detail)
        if self._record is not None:
            self._record({"t": round(ev.t - self._t0, 4), "event": kind, "drone": drone, "detail": detail,
                          **{k: v for k, v in ev.data.items() if k not in ("t", "event", "drone", "detail")}})

    def _write_rows(self, now: float) -> None:
        if self._record is None:
            return
        roles_by_drone = {d: self.assignment.role_of_drone(d) for d in self.drones}
        for d in self.drones.values():
            tel = d.link.telemetry()
            role = roles_by_drone.get(d.id)
            sp = d.setpoint
            self._record({
                "t": round(now - self._t0, 4), "drone": d.id, "role": role.label if role is not None else None,
                "actor": self.assignment.by_drone.get(d.id), "state": d.status.value,
                "position": None if tel is None else [round(float(c), 4) for c in tel.position],
                "setpoint": None if sp is None else [round(float(c), 4) for c in sp],
                "setpoint_age": None if sp is None else round(now - d.setpoint_t, 4),
                "battery": None if tel is None else round(float(tel.battery), 3),
                "link_quality": None if tel is None else round(float(tel.link_quality), 3),
                "telemetry_age": round(min(d.link.telemetry_age(now), 999.0), 4),
            })


class JsonlRecorder:
    """Writes flight-log rows as JSON lines (thread-safe) and keeps them for plotting. Each row is written
    whole and flushed, so a log cut short (an error, Ctrl-C, a killed process) ends with its last complete row:
    a flight recorder keeps what happened up to the end, and never holds half a line."""

    def __init__(self, path: str | Path | None = None, keep: bool = True) -> None:
        self.path = Path(path) if path else None
        self.rows: list[dict] = []
        self.keep = keep
        self._lock = threading.Lock()
        self._fh = None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = self.path.open("w")

    def __call__(self, row: dict) -> None:
        line = json.dumps(row, separators=(",", ":"), default=str)
        with self._lock:
            if self.keep:
                self.rows.append(row)
            if self._fh is not None:
                self._fh.write(line + "\n")
                self._fh.flush()

    def close(self) -> None:
        with self._lock:
            if self._fh is not None:
                self._fh.close()
                self._fh = None


def close_links(links: Iterable[Link]) -> None:
    """Close links in parallel (cflib's close waits about 1 s for its receive thread, per link)."""
    threads = [threading.Thread(target=link.close, name=f"close {link.uri}") for link in links]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=5.0)
