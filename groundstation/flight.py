"""Flight operations: preflight, staggered takeoff, the mission's setpoint stream, failsafes, landing.

``FlightSession`` is a context manager over open ``Link`` s (one per drone)::

    with FlightSession(links, teams, fence, FlightConfig(), actors=manifest_actors) as session:
        session.preflight(models_spec_hash=manifest.spec.hash, spec_hash=spec.hash)
        session.assign_roles()
        session.takeoff()
        session.start_mission()            # velocity commands from the per-drone runtimes now fly
        ...                                # session.set_command(drone_id, (vx, vy), t) from each runtime
    # every drone still in the air lands on exit, on an exception and on Ctrl-C

This module is the session's lifecycle and its operator commands. The session is put together from parts,
one responsibility each, that share the state declared in ``flight_records.SessionCore``:

=======================  ===============================================================================
``setpoint_path``        runtime command -> separation filter -> geofence -> link, on each receive thread
``failsafes``            the supervisor thread: link loss, stale position, low battery, agent faults,
                         fence breaches; follows every landing to the ground
``role_repair``          which drone flies which actor, at the start and after a drone leaves
``flight_records``       status changes, events, the flight log (``JsonlRecorder``)
``flight_types``         ``FlightConfig`` (``[flight]``), ``DroneStatus``, the per-drone state, events
=======================  ===============================================================================
"""
from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from groundstation import roles as roles_mod
from groundstation.failsafes import FailsafeSupervisor
from groundstation.flight_records import JsonlRecorder
from groundstation.flight_types import (AIRBORNE, DroneState, DroneStatus, FlightConfig, FlightEvent,
                                        PreflightError)
from groundstation.link import FlightState, Link, LinkError
from groundstation.positioning import PositionTracker
from groundstation.safety import FenceConfig, Geofence, in_safe_set
from groundstation.separation import SeparationConfig
from groundstation.setpoint_path import SetpointPath

__all__ = ["AIRBORNE", "DroneStatus", "FlightConfig", "FlightEvent", "FlightSession", "JsonlRecorder",
           "PreflightError", "close_links"]

log = logging.getLogger(__name__)


class FlightSession(SetpointPath, FailsafeSupervisor):
    """Flight operations over open links. See the module docstring.

    ``links``: drone id -> open ``Link``. ``teams``: drone id -> ``"pursuer"`` (flies pursuer and scout
    actors) or ``"evader"``. ``actors``: the model manifest's actors (``roles.parse_actors`` input).
    ``record``: called with one dict per flight-log row and per event (``JsonlRecorder`` writes them).
    ``separation_process``: the separation filter's joint solve runs in a process of its own instead of a thread
    of this interpreter (``JointFilter(process=True)``: the demo and ``swarm-gs fly``).
    The session owns neither the links nor the simulator: close them after the session has exited.
    """

    def __init__(self, links: Mapping[str, Link], teams: Mapping[str, str], fence: FenceConfig,
                 config: FlightConfig = FlightConfig(), actors: Iterable[Any] = (),
                 tracker: PositionTracker | None = None,
                 record: Callable[[dict], None] | None = None, latency_probe: bool = False,
                 separation: SeparationConfig = SeparationConfig(), separation_process: bool = False) -> None:
        if not links:
            raise ValueError("FlightSession needs at least one link")
        missing = sorted(set(links) - set(teams))
        if missing:
            raise ValueError(f"drone {missing[0]}: no team given: pass teams[{missing[0]!r}] = 'pursuer' or 'evader'")
        self.config = config
        self.fence = fence
        self.geofence = Geofence(fence)
        self.tracker = tracker or PositionTracker(stale_after=config.position_stale_after)
        self.actors = roles_mod.parse_actors(actors)
        self.drones = {d: DroneState(d, link, teams[d]) for d, link in links.items()}
        self.events: list[FlightEvent] = []
        self._event_rows: list[dict[str, Any]] = []
        """``events`` as the live view shows them, built once each (an event never changes)."""
        self._event_rows_lock = threading.Lock()
        self.height = self.geofence.clamp_height(config.height)
        self._record = record
        self._lock = threading.RLock()
        self._mission = False
        self._init_roles()
        self._init_setpoint_path(links, separation, latency_probe, separation_process)
        self._t0 = time.monotonic()
        self._init_supervisor()

    # ---- context manager ---------------------------------------------------------------------------

    def __enter__(self) -> "FlightSession":
        self._attach_setpoints()
        self._start_supervisor()
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
            self._stop_supervisor()
            if self.separation is not None:
                self.separation.stop()
            self._detach_setpoints()

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
        with self._event_rows_lock:
            rows = self._event_rows
            for i in range(len(rows), n):  # only the events that are new since the last snapshot
                e = self.events[i]
                rows.append({"i": i, "t": round(e.t - self._t0, 3), "drone": e.drone, "kind": e.kind,
                             "detail": e.detail})
            first = max(events_since, n - max_events, 0)
            events = rows[first:n]
        return {"t": round(now - self._t0, 3), "mission": self._mission, "drones": drones, "events": events,
                "n_events": n}

    # ---- preflight -----------------------------------------------------------------------

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

    def _preflight_problem(self, d: DroneState, cfg: FlightConfig) -> str | None:
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
        """Land every drone in the air; with ``wait`` block until each reports landed or ``land_timeout``
        passes. Returns the final statuses.

        A drone whose link is lost is waited for too while it may still answer (heard within the last
        ``land_timeout``): a link that drops out for a moment during the landing (a loaded ground station, a
        radio fade) comes back, and the drone is then landed and seen on the ground, instead of this returning
        at once and the caller closing a link to a drone still in the air. A drone silent for longer is left
        to its own firmware (the land commands went out all along)."""
        self._mission = False
        for d in self.drones.values():
            if d.status in AIRBORNE:
                self._begin_landing(d, reason)
        if wait:
            deadline = time.monotonic() + self.config.land_timeout
            while (now := time.monotonic()) < deadline:
                self._check_landings(now)
                if not any(self._coming_down(d, now) for d in self.drones.values()):
                    break
                time.sleep(0.05)
        return self.statuses()

    def _coming_down(self, d: DroneState, now: float) -> bool:
        """``land_all`` waits for this drone: it is landing, or lost but heard within ``land_timeout``."""
        if d.status is DroneStatus.LANDING:
            return True
        return d.status is DroneStatus.LOST and d.link.telemetry_age(now) < self.config.land_timeout

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


def close_links(links: Iterable[Link]) -> None:
    """Close links in parallel (cflib's close waits about 1 s for its receive thread, per link)."""
    threads = [threading.Thread(target=link.close, name=f"close {link.uri}") for link in links]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=5.0)
