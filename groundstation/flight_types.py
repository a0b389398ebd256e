"""The flight session's vocabulary: its settings, the drone statuses, the per-drone state, events and errors.

``FlightConfig`` is the ``[flight]`` TOML table; ``DroneState`` is what the session keeps per drone (written by
the supervisor and the receive threads under the drone's ``lock``, read whole by observers); the rest are the
values that the session's parts (``flight``, ``setpoint_path``, ``failsafes``, ``role_repair``,
``flight_records``) pass between them.
"""
from __future__ import annotations

import enum
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from groundstation.link import Link
from runtime.spec import SpecError, from_mapping, load_toml


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
class DroneState:
    """One drone as the session keeps it."""

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
