"""Role repair of the flight session: the first assignment of the model's actors to drones, and a new one
whenever a drone leaves the mission (``roles.assign_roles`` / ``roles.reassign``, pure functions, do the work).

An actor whose model itself failed (``report_agent_fault(..., retire_actor=True)``) is retired: no other
drone takes it over. Listeners (``role_listeners``: the per-drone runtimes) hear of every new assignment.
"""
from __future__ import annotations

import logging
import time
from typing import Callable

from groundstation import roles as roles_mod
from groundstation.flight_records import SessionCore
from groundstation.flight_types import AIRBORNE, DroneStatus
from groundstation.positioning import battery_fraction
from runtime.spec import Role

log = logging.getLogger(__name__)


class RoleRepair(SessionCore):
    """Who flies which actor."""

    def _init_roles(self) -> None:
        self.assignment = roles_mod.Assignment(self.actors, {})
        self.role_changes: list[roles_mod.RoleChange] = []
        self.role_listeners: list[Callable[[roles_mod.Assignment], None]] = []
        self._retired: set[str] = set()

    def assign_roles(self) -> roles_mod.Assignment:
        """Initial role assignment over the drones that passed preflight (by battery and distance)."""
        with self._lock:
            infos = self._drone_infos(for_takeoff=True)
            self.assignment = roles_mod.assign_roles(self.actors, infos, distance_scale=self._distance_scale())
            now = time.monotonic()
            for d in self.drones.values():
                d.actor_since = now
            self._event(None, "roles_assigned", "", {"by_drone": self.assignment.by_drone})
        self._notify_roles()
        return self.assignment

    def _distance_scale(self) -> float:
        """What the role cost divides distances by: the flight area's side, the fence's wider extent [m]."""
        lo, hi = self.fence.bounds()
        return float(max(hi[0] - lo[0], hi[1] - lo[1]))

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
                                              low_battery=battery_fraction(self.config.low_battery_v),
                                              distance_scale=self._distance_scale())
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
