"""The safety geofence every setpoint passes before it leaves the ground station.

The fence itself (its configuration, geometry, ``check_position``, ``in_safe_set``, ``clamp_position``) is in
``fence``; this module holds the velocity rule and the gate.

The pure functions (``clamp_path``, ``limit_velocity``, and ``fence``'s ``clamp_position`` and
``check_position``) hold the geometry, compiled in ``fence_geometry`` (about 10 us per setpoint instead of
about 250 us: ``tests/benchmarks/test_bench_fence.py``); ``FenceGuard`` is the per-drone hold-then-land state machine;
``Geofence`` wraps both and is the one object that setpoints go through.

Velocity rule: a velocity ``v`` along unit direction ``u`` from position ``p`` is allowed when the straight
path from ``p`` along ``u`` stays in the safe set for the longer of two futures, otherwise its speed is cut
to the largest that does:

* the ground station keeps commanding: the drone flies ``v`` for a control period ``dt`` and then brakes
  at ``max_decel``: ``|v| dt + |v|^2 / (2 max_decel)``;
* the ground station falls silent right after this setpoint: the Crazyflie flies it until its setpoint
  watchdog levels it out (0.5 s), then coasts with horizontal control off until the motors stop at 2 s
  (``crazyflie-firmware`` ``supervisor.c``; ``cf_firmware.WDT_SHUTDOWN_S``). Drag only slows the coast and a
  velocity-mode height keeps its speed, so ``|v| coast_time`` bounds the path: horizontally the coast stays
  on the ray, vertically within ``|v_z| coast_time``, and the safe set is a prism, so the straight segment
  of that length decides.

Starting in the safe set, a drone flown only by limited velocities therefore never leaves it, whatever is
commanded and whenever the commands stop. The vehicle's own tracking error is what ``margin`` is for.
"""
from __future__ import annotations

import enum
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from groundstation import fence_geometry as fg
from groundstation.fence import (FAR, TOL, FenceConfig, FenceStatus, KeepOut, as_point, check_position,
                                 clamp_position, geometry, in_safe_set, point3)

__all__ = ["FenceConfig", "FenceGuard", "FenceStats", "FenceStatus", "FilteredSetpoint", "Geofence", "GuardState",
           "KeepOut", "check_position", "clamp_path", "clamp_position", "free_distance", "in_safe_set",
           "limit_velocity", "max_safe_speed"]

log = logging.getLogger(__name__)

_BRAKE_SLACK = fg.BRAKE_SLACK
"""Distance [m] kept back from a boundary by the velocity limit, against rounding."""


# --------------------------------------------------------------------------------------------------
# the velocity rule (compiled: ``fence_geometry``)

def free_distance(fence: FenceConfig, p: np.ndarray, u: np.ndarray) -> float:
    """Distance [m] from ``p`` (in the safe set) along unit vector ``u`` to the safe set's boundary."""
    return fg.free_distance(geometry(fence).packed, float(p[0]), float(p[1]), float(p[2]), float(u[0]),
                            float(u[1]), float(u[2]))


def max_safe_speed(distance: float, dt: float, max_decel: float, coast_time: float = 0.0) -> float:
    """Largest speed s [m/s] with ``s dt + s^2 / (2 max_decel) <= distance`` and ``s coast_time <= distance``."""
    return fg.max_safe_speed(float(distance), float(dt), float(max_decel), float(coast_time))


def limit_velocity(fence: FenceConfig, position: Sequence[float] | np.ndarray | None,
                   v: Sequence[float] | np.ndarray | None, dt: float) -> np.ndarray:
    """Velocity setpoint ``v`` [m/s] cut so that a drone at ``position`` [m] flying it for ``dt`` [s] and then
    braking at ``fence.max_decel``, or flying and coasting on it for ``fence.coast_time``, stays in the safe
    set.

    The direction is kept and only the speed is reduced (to at most ``fence.max_speed``). From a position
    outside the safe set only the part of ``v`` that heads for the nearest safe point is kept, slow enough to
    stop there. Missing or non-finite ``position``, ``v`` or ``dt``, or ``dt < 0``, give zero (hover)."""
    out = np.zeros(3)
    p = point3(position)
    w = point3(v)
    if p is None or w is None or not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt >= 0):
        return out
    fg.limit_velocity(geometry(fence).packed, p, w, float(dt), fence.max_speed, fence.max_decel,
                      fence.coast_time, FAR, out)
    return out


def clamp_path(fence: FenceConfig, start: Sequence[float] | np.ndarray | None,
               target: Sequence[float] | np.ndarray | None,
               fallback: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """Position setpoint ``target`` [m] clamped into the safe set and, when the drone's position ``start``
    is known and safe, pulled back along the straight line from ``start`` so that the path there does not
    cut through a keep-out circle or a corner of the margin. Non-finite ``target`` falls back as in
    ``clamp_position``."""
    q = clamp_position(fence, target, fallback if fallback is not None else start)
    s = as_point(start)
    if s is None:
        return q
    if not in_safe_set(fence, s):
        s = clamp_position(fence, s)  # a drone in the margin starts its path from the nearest safe point
    d = q - s
    n = float(np.linalg.norm(d))
    if n <= TOL:
        return q
    free = free_distance(fence, s, d / n) - _BRAKE_SLACK
    if free >= n:
        return q
    return s + d / n * max(free, 0.0)


# --------------------------------------------------------------------------------------------------
# hold-then-land


class GuardState(enum.Enum):
    OK = "ok"
    """Setpoints are filtered and sent."""
    HOLD = "hold"
    """Measured outside the fence: hover (zero velocity, or the nearest safe point for position setpoints)."""
    LAND = "land"
    """Outside for longer than ``hold_time``: the caller must land the drone. Latched until ``reset``."""


class FenceGuard:
    """One drone's fence state machine: measured OUTSIDE -> HOLD; back in -> OK; OUTSIDE for ``hold_time``
    -> LAND (latched)."""

    def __init__(self, fence: FenceConfig, drone_id: str = "") -> None:
        self.fence = fence
        self.drone_id = drone_id
        self.state = GuardState.OK
        self._since: float | None = None

    def update(self, status: FenceStatus, t: float) -> GuardState:
        """Feed one measurement's status at time ``t`` [s, monotonic]; returns the new state."""
        old = self.state
        if self.state is GuardState.LAND:
            return self.state
        if status is FenceStatus.OUTSIDE:
            if self.state is GuardState.OK:
                self.state, self._since = GuardState.HOLD, t
            elif self._since is not None and t - self._since >= self.fence.hold_time:
                self.state = GuardState.LAND
        elif self.state is GuardState.HOLD:
            self.state, self._since = GuardState.OK, None
        if self.state is not old:
            log.warning("fence guard %s: %s -> %s (measured %s)", self.drone_id, old.value, self.state.value,
                        status.value)
        return self.state

    def reset(self) -> None:
        """Back to OK (after the drone has landed and been checked)."""
        if self.state is not GuardState.OK:
            log.info("fence guard %s: reset from %s", self.drone_id, self.state.value)
        self.state, self._since = GuardState.OK, None


@dataclass(frozen=True)
class FilteredSetpoint:
    """What the geofence lets through for one setpoint."""

    state: GuardState
    """OK: send ``value``. HOLD: send ``value`` (a hover). LAND: send nothing, land the drone."""
    value: np.ndarray
    """The setpoint to send [m] or [m/s], always inside the fence's limits."""
    changed: bool
    """Whether the geofence altered the requested setpoint."""


@dataclass
class FenceStats:
    """Counters per drone."""

    setpoints: int = 0
    clamped: int = 0
    """Setpoints the fence altered."""
    non_finite: int = 0
    """Setpoints or measurements that were NaN, inf or missing."""
    violations: int = 0
    """Times the drone was measured outside the fence (entries into HOLD)."""
    landings: int = 0
    """Times the guard ordered a landing."""


class Geofence:
    """The gate that every setpoint passes before it is sent. Thread-safe; one ``FenceGuard`` per drone.

    >>> gf = Geofence(FenceConfig())
    >>> out = gf.filter_velocity("cf1", measured_pos=(0, 0, 1), v=(5, 0, 0), dt=0.1)
    >>> out.state, out.value  # speed cut to fence.max_speed or less
    """

    def __init__(self, fence: FenceConfig, clock: Callable[[], float] = time.monotonic) -> None:
        self.fence = fence
        self.clock = clock
        self._guards: dict[str, FenceGuard] = {}
        self._stats: dict[str, FenceStats] = {}
        self._last_position: dict[str, np.ndarray] = {}
        self._lock = threading.Lock()
        # numba compiles the kernels (or loads them from its cache) on their first call: here, not in the
        # first setpoint of a flight
        limit_velocity(fence, fence.home, np.ones(3), 0.1)
        limit_velocity(fence, fence.home + (1e3, 0.0, 0.0), np.ones(3), 0.1)
        check_position(fence, fence.home)

    def guard(self, drone_id: str) -> FenceGuard:
        with self._lock:
            return self._guard(drone_id)

    def stats(self, drone_id: str) -> FenceStats:
        with self._lock:
            return self._stats.setdefault(drone_id, FenceStats())

    def reset(self, drone_id: str) -> None:
        with self._lock:
            self._guard(drone_id).reset()

    def _guard(self, drone_id: str) -> FenceGuard:
        if drone_id not in self._guards:
            self._guards[drone_id] = FenceGuard(self.fence, drone_id)
            self._stats[drone_id] = FenceStats()
        return self._guards[drone_id]

    def _observe(self, drone_id: str, measured_pos: object,
                 status: FenceStatus | None = None) -> tuple[GuardState, FenceStats]:
        guard = self._guard(drone_id)
        st = self._stats[drone_id]
        before = guard.state
        if status is None:
            status = check_position(self.fence, measured_pos)  # type: ignore[arg-type]
        if point3(measured_pos) is None:
            st.non_finite += 1
        state = guard.update(status, self.clock())
        if state is GuardState.HOLD and before is GuardState.OK:
            st.violations += 1
        if state is GuardState.LAND and before is not GuardState.LAND:
            st.landings += 1
        st.setpoints += 1
        return state, st

    def filter_velocity(self, drone_id: str, measured_pos: Sequence[float] | np.ndarray | None,
                        v: Sequence[float] | np.ndarray | None, dt: float) -> FilteredSetpoint:
        """Velocity setpoint ``v`` [m/s] for the next ``dt`` [s] of a drone measured at ``measured_pos`` [m].

        The geometry (pure functions of the fence) runs outside the lock, which guards only the guard's state
        and the counters: every link's receive thread passes here, and with the geometry inside one shared lock
        they queued behind each other (measured in the 12-drone demo: setpoint p99 in the ground station
        59-65 ms with it inside, 7-16 ms outside, same machine and load)."""
        status = check_position(self.fence, measured_pos)  # type: ignore[arg-type]
        req = point3(v)
        with self._lock:
            state, st = self._observe(drone_id, measured_pos, status)
            if req is None:
                st.non_finite += 1
        if state is not GuardState.OK:
            return FilteredSetpoint(state, np.zeros(3), True)
        out = limit_velocity(self.fence, measured_pos, v, dt)
        changed = req is None or max(abs(a - b) for a, b in zip(out.tolist(), req.tolist())) > 1e-12
        if changed:
            with self._lock:
                st.clamped += 1
        return FilteredSetpoint(state, out, changed)

    def filter_position(self, drone_id: str, measured_pos: Sequence[float] | np.ndarray | None,
                        p: Sequence[float] | np.ndarray | None) -> FilteredSetpoint:
        """Position setpoint ``p`` [m] of a drone measured at ``measured_pos`` [m]. Non-finite ``p`` falls back
        to the drone's last safe position setpoint, then to its measured position, then to ``fence.home``."""
        with self._lock:
            state, st = self._observe(drone_id, measured_pos)
            last = self._last_position.get(drone_id)
            if as_point(p) is None:
                st.non_finite += 1
            if state is GuardState.LAND:
                return FilteredSetpoint(state, clamp_position(self.fence, measured_pos, last), True)
            if state is GuardState.HOLD:
                out = clamp_position(self.fence, measured_pos, last)
            else:
                fb = last if last is not None else as_point(measured_pos)
                out = clamp_path(self.fence, measured_pos, p, fb) if as_point(p) is not None \
                    else clamp_position(self.fence, fb)
            self._last_position[drone_id] = out
            req = as_point(p)
            changed = req is None or not np.allclose(out, req, rtol=0, atol=1e-12)
            st.clamped += int(changed)
            return FilteredSetpoint(state, out, changed)

    def clamp_height(self, height: float) -> float:
        """A takeoff height [m] inside the altitude band."""
        lo, hi = self.fence.z_band
        if not isinstance(height, (int, float)) or not math.isfinite(height):
            return lo
        return min(max(float(height), lo), hi)
