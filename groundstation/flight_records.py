"""What every part of the flight session shares, and what it records.

``SessionCore`` is the base of the session's parts (``setpoint_path.SetpointPath``,
``failsafes.FailsafeSupervisor``, ``role_repair.RoleRepair``; ``flight.FlightSession`` puts them together and
sets every attribute declared here in its ``__init__``). It owns status changes and the flight log: every
status change is an event, every event and every ``record_rate`` row goes to ``record`` (``JsonlRecorder``
or ``mcap_log.McapRecorder``).
"""
from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Any, Callable, Mapping

from groundstation import roles as roles_mod
from groundstation.flight_types import DroneState, DroneStatus, FlightConfig, FlightEvent
from groundstation.positioning import PositionTracker
from groundstation.safety import FenceConfig, Geofence

log = logging.getLogger(__name__)


class SessionCore:
    """The session's shared state (set by ``FlightSession.__init__``) and its records."""

    config: FlightConfig
    fence: FenceConfig
    geofence: Geofence
    tracker: PositionTracker
    drones: dict[str, DroneState]
    actors: tuple[roles_mod.Actor, ...]
    assignment: roles_mod.Assignment
    events: list[FlightEvent]
    height: float
    """Mission altitude [m], inside the fence's altitude band."""
    _record: Callable[[dict], None] | None
    _lock: threading.RLock
    _mission: bool
    _t0: float
    """time.monotonic() when the session was created: the flight log's time zero."""

    def _set_status(self, d: DroneState, status: DroneStatus, reason: str = "") -> None:
        if d.status is status:
            return
        old = d.status
        d.status, d.reason, d.status_since = status, reason, time.monotonic()
        self._event(d.id, "status", f"{old.value} -> {status.value}" + (f" ({reason})" if reason else ""),
                    {"from": old.value, "to": status.value})

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
