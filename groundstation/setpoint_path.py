"""The setpoint path of the flight session: runtime command -> separation filter -> geofence -> link.

The per-drone runtimes hand in horizontal velocity commands (``FlightSession.set_command``); this part turns
them into setpoints at ``setpoint_rate``. A setpoint is computed when a drone's telemetry arrives and its
setpoint is due, from the measurement that just arrived (this keeps measurement-to-setpoint latency to the
processing time): horizontal command, through the separation filter (``separation.JointFilter``: every
drone's latest tracker position and velocity, solved jointly once per setpoint period on its own thread; the
receive threads read its cache), + an altitude-hold term, through the geofence (``safety.Geofence``), then
``link.send_velocity``. Nothing else sends setpoints. A holding drone's zero velocity needs no filter (zero is
the filter's own brake); to the filter it, and every drone not flying the mission, is an obstacle.
"""
from __future__ import annotations

import collections
import logging
import time
from typing import Any, Callable, Mapping

import numpy as np

from groundstation.flight_records import SessionCore
from groundstation.flight_types import DroneState, DroneStatus
from groundstation.link import Link, LinkError, Telemetry
from groundstation.safety import GuardState, limit_velocity
from groundstation.separation import JointFilter, Limits, SeparationConfig, Snapshot

log = logging.getLogger(__name__)


class SetpointPath(SessionCore):
    """Each link's receive thread computes and sends its drone's setpoints (``_make_callback``)."""

    def _init_setpoint_path(self, links: Mapping[str, Link], separation: SeparationConfig,
                            latency_probe: bool, separation_process: bool = False) -> None:
        if latency_probe and not all(link.uri.startswith("udp://") for link in links.values()):
            raise ValueError("latency_probe puts a timestamp in the yaw rate: simulated drones (udp://) only")
        self.latency_probe = latency_probe
        """Simulator benchmark: every velocity setpoint's yaw rate [rad/s] carries the vehicle timestamp (mod
        2^16 ms) of the measurement it answers, so the simulator can time measurement-to-setpoint at the
        drone (``SimSwarm(latency_probe=True)``). A real drone would spin: refused for other than udp://."""
        self.latencies = collections.deque(maxlen=200_000)
        """Measurement-to-setpoint delays [s]: telemetry arrival to the setpoint handed to the link."""
        self._callbacks: dict[str, Callable[[Telemetry], None]] = {}
        self._period = 1.0 / self.config.setpoint_rate
        self.separation_config = separation
        self.separation: JointFilter | None = None
        """The separation filter; None only with ``separation.enabled = False`` (comparisons)."""
        if separation.enabled:
            # latency: the cached solution's age (one period) + the measurement's age and the link (one more)
            limits = Limits(separation.min_distance, self._period, self.fence.max_decel, self.fence.max_speed,
                            latency=2.0 * self._period)
            self.separation = JointFilter(limits, self._separation_snapshot, interval=self._period,
                                          process=separation_process)

    def _attach_setpoints(self) -> None:
        """Start computing setpoints: the tracker and then the setpoint callback on every link."""
        for d in self.drones.values():
            self.tracker.attach(d.id, d.link)  # registered first: the setpoint callback reads the tracker
            cb = self._make_callback(d)
            d.link.add_telemetry_callback(cb)
            self._callbacks[d.id] = cb

    def _detach_setpoints(self) -> None:
        for d in self.drones.values():
            cb = self._callbacks.pop(d.id, None)
            if cb is not None:
                try:
                    d.link.remove_telemetry_callback(cb)
                except ValueError:
                    log.debug("%s: setpoint callback was already removed", d.id)
            self.tracker.detach(d.id)

    def _make_callback(self, d: DroneState) -> Callable[[Telemetry], None]:
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

    def _desired(self, d: DroneState) -> np.ndarray:
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

    def _last_position(self, d: DroneState) -> np.ndarray:
        s = self.tracker.get(d.id)
        return np.array(s.position) if s is not None else self.fence.home
