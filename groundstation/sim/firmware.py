"""What the Crazyflie firmware does with the commands it receives: commander priorities, the setpoint
watchdog, the high-level commander's planner, the supervisor's states, the emergency stops, the estimator
reset. One ``Firmware`` per simulated drone; no sockets, no clocks (every call takes ``now`` [s]).

Safety behaviour, as in crazyflie-firmware (``supervisor.c``, ``commander.c``):

* a streamed (low-level) setpoint older than 0.5 s while flying: level out and hold the height;
* older than 2 s: motors off, supervisor locked; only a reboot clears it;
* ``notify_setpoint_stop(remain_valid_ms)`` ages the last streamed setpoint so that it stays valid for
  ``remain_valid_ms`` and lets the high-level commander take over;
* the high-level commander generates its own setpoints on board, so it is not subject to the watchdog and
  holds its last target when its trajectory ends;
* emergency stop (and its watchdog, 1 s): motors off, locked.
"""
from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

import numpy as np

from groundstation.sim.flight_model import QuadParams, Segment

logger = logging.getLogger(__name__)

WDT_WARNING_S = 0.5
"""COMMANDER_WDT_TIMEOUT_STABILIZE [s]."""
WDT_SHUTDOWN_S = 2.0
"""COMMANDER_WDT_TIMEOUT_SHUTDOWN [s]."""
ESTOP_WATCHDOG_S = 1.0
"""DEFAULT_EMERGENCY_STOP_WATCHDOG_TIMEOUT [s]."""
EXTPOS_FRESH_S = 0.5
"""External positions younger than this dominate the position estimate [s]."""
KALMAN_CONVERGE_S = 0.2
"""Time constant of the position variance after an estimator reset [s]."""
LANDED_HEIGHT_M = 0.05
"""A landing that ends at or below this height above the floor turns the motors off [m]."""


class SupervisorState(enum.Enum):
    DISARMED = "disarmed"
    READY = "ready"
    FLYING = "flying"
    LEVEL_OUT = "level_out"
    LOCKED = "locked"


class Mode(enum.Enum):
    IDLE = "idle"
    POSITION = "position"
    VELOCITY = "velocity"
    HOVER = "hover"
    HIGH_LEVEL = "high_level"


# supervisor.info bits (crazyflie-firmware supervisor.c, cflib supervisor.py)
BIT_CAN_BE_ARMED, BIT_IS_ARMED, BIT_AUTO_ARMED, BIT_CAN_FLY, BIT_IS_FLYING = 0, 1, 2, 3, 4
BIT_IS_LOCKED, BIT_HL_ACTIVE, BIT_HL_FINISHED, BIT_HL_DISABLED = 6, 8, 9, 10


@dataclass
class _Streamed:
    mode: Mode
    target: tuple[float, float, float, float]
    """Mode-specific: (x, y, z, yaw_deg), (vx, vy, vz, yaw_rate_deg) or (vx_body, vy_body, yaw_rate_deg, z)."""
    stamp: float
    """Time the setpoint counts as received (moved back by notify-setpoint-stop) [s]."""
    relaxed: bool = False
    """After notify-setpoint-stop: the high-level commander may take over."""


class Firmware:
    """Onboard logic of one drone."""

    def __init__(self, params: QuadParams, now: float) -> None:
        self.params = params
        self.state = SupervisorState.READY  # auto-arming, as on a stock Crazyflie 2.x
        self.mode = Mode.IDLE
        self.group_mask = 0
        self._streamed: _Streamed | None = None
        self._segment: Segment | None = None
        self._segment_yaw = (0.0, 0.0)
        self._landing = False
        self._hold_z = 0.0
        self._estop_deadline: float | None = None
        self._extpos_time = -math.inf
        self.extpos = np.zeros(3)
        self._reset_time = now - 10.0 * KALMAN_CONVERGE_S  # converged at boot

    # ---- streamed (generic commander) setpoints -------------------------------------------------

    def setpoint(self, now: float, mode: Mode, target: tuple[float, float, float, float]) -> None:
        if self.state in (SupervisorState.LOCKED, SupervisorState.DISARMED):
            return
        self._streamed = _Streamed(mode, target, now)
        self.mode = mode
        self._segment = None
        if self.state in (SupervisorState.READY, SupervisorState.LEVEL_OUT):
            self.state = SupervisorState.FLYING

    def setpoint_stop(self, now: float) -> None:
        """Null setpoint: motors off, the drone drops."""
        self._streamed = None
        self._segment = None
        self.mode = Mode.IDLE

    def notify_setpoint_stop(self, now: float, remain_valid_s: float) -> None:
        if self._streamed is None:
            return
        setback = min(WDT_SHUTDOWN_S - remain_valid_s, now)
        self._streamed.stamp = now - max(setback, 0.0)
        self._streamed.relaxed = True

    # ---- high-level commander ---------------------------------------------------------------------

    def _in_group(self, group_mask: int) -> bool:
        return group_mask == 0 or (group_mask & self.group_mask) != 0

    def _hl_may_take_over(self, now: float) -> bool:
        s = self._streamed
        if self.mode in (Mode.IDLE, Mode.HIGH_LEVEL) or s is None:
            return True
        return s.relaxed or now - s.stamp > WDT_WARNING_S

    def hl_takeoff(self, now: float, group_mask: int, pos: np.ndarray, yaw_deg: float, height: float,
                   duration: float, target_yaw_deg: float | None) -> None:
        if not self._in_group(group_mask):
            return
        if self.state not in (SupervisorState.READY, SupervisorState.FLYING, SupervisorState.LEVEL_OUT):
            logger.info("takeoff refused in supervisor state %s", self.state.value)
            return
        if self.mode is Mode.HIGH_LEVEL and not self._landing:
            logger.info("takeoff refused: the high-level commander is already flying")
            return
        if not self._hl_may_take_over(now):
            logger.info("takeoff refused: a streamed setpoint has priority (send notify_setpoint_stop)")
            return
        end = (float(pos[0]), float(pos[1]), float(height))
        self._plan(now, pos, end, duration, yaw_deg, yaw_deg if target_yaw_deg is None else target_yaw_deg)
        self._landing = False
        self.state = SupervisorState.FLYING

    def hl_land(self, now: float, group_mask: int, pos: np.ndarray, yaw_deg: float, height: float,
                duration: float, target_yaw_deg: float | None) -> None:
        if not self._in_group(group_mask) or self.state not in (SupervisorState.FLYING,
                                                                 SupervisorState.LEVEL_OUT):
            return
        if not self._hl_may_take_over(now):
            logger.info("land refused: a streamed setpoint has priority (send notify_setpoint_stop)")
            return
        end = (float(pos[0]), float(pos[1]), float(height))
        self._plan(now, pos, end, duration, yaw_deg, yaw_deg if target_yaw_deg is None else target_yaw_deg)
        self._landing = True
        self.state = SupervisorState.FLYING

    def hl_go_to(self, now: float, group_mask: int, pos: np.ndarray, yaw_deg: float,
                 goal: tuple[float, float, float], goal_yaw_deg: float, duration: float, relative: bool,
                 linear: bool) -> None:
        if not self._in_group(group_mask) or self.state not in (SupervisorState.FLYING,
                                                                 SupervisorState.LEVEL_OUT):
            return
        if not self._hl_may_take_over(now):
            logger.info("go_to refused: a streamed setpoint has priority (send notify_setpoint_stop)")
            return
        start = self._hl_reference(now, pos)
        end = tuple(float(g) for g in goal)
        if relative:
            end = (start[0] + end[0], start[1] + end[1], start[2] + end[2])
            goal_yaw_deg += yaw_deg
        self._plan(now, start, end, duration, yaw_deg, goal_yaw_deg, linear)
        self._landing = False
        self.state = SupervisorState.FLYING

    def hl_stop(self, now: float, group_mask: int) -> None:
        if self._in_group(group_mask) and self.mode is Mode.HIGH_LEVEL:
            self._segment = None
            self.mode = Mode.IDLE

    def _hl_reference(self, now: float, pos: np.ndarray) -> np.ndarray:
        """Plan from the current reference when already on a trajectory (as the firmware planner does)."""
        if self.mode is Mode.HIGH_LEVEL and self._segment is not None:
            return self._segment.sample(now)[0]
        return np.asarray(pos, dtype=float)

    def _plan(self, now, start, end, duration, yaw0, yaw1, linear=False) -> None:
        start = tuple(float(s) for s in start)
        self._segment = Segment(now, max(float(duration), 0.0), start, tuple(end), linear)
        self._segment_yaw = (yaw0, yaw1)
        self._streamed = None
        self.mode = Mode.HIGH_LEVEL

    # ---- supervisor, localization, estimator ------------------------------------------------------

    def emergency_stop(self, now: float) -> None:
        if self.state is not SupervisorState.LOCKED:
            logger.info("emergency stop: motors off, locked (reboot required)")
        self._lock()

    def emergency_stop_watchdog(self, now: float) -> None:
        self._estop_deadline = now + ESTOP_WATCHDOG_S

    def arm(self, do_arm: bool) -> tuple[bool, bool]:
        """Supervisor arming request; returns (success, is_armed)."""
        if self.state is SupervisorState.LOCKED:
            return (not do_arm), False
        if do_arm and self.state is SupervisorState.DISARMED:
            self.state = SupervisorState.READY
        elif not do_arm and self.state is SupervisorState.READY:
            self.state = SupervisorState.DISARMED
        elif not do_arm:
            return False, True  # cannot disarm in flight
        return True, self.armed

    def set_extpos(self, now: float, xyz: tuple[float, float, float]) -> None:
        self.extpos = np.asarray(xyz, dtype=float)
        self._extpos_time = now

    def extpos_fresh(self, now: float) -> bool:
        return now - self._extpos_time < EXTPOS_FRESH_S

    def extpos_age(self, now: float) -> float:
        """Seconds since the latest external position [s]."""
        return now - self._extpos_time

    def reset_estimation(self, now: float) -> None:
        self._reset_time = now

    def position_variance(self, now: float) -> tuple[float, float, float]:
        """kalman.varPX/PY/PZ [m^2]: 1 m^2 after a reset, converging to the positioning noise."""
        p = self.params
        decay = math.exp(-(now - self._reset_time) / KALMAN_CONVERGE_S)
        ss = (p.lps_sigma_xy**2, p.lps_sigma_xy**2, p.lps_sigma_z**2)
        return tuple(s + (1.0 - s) * decay for s in ss)

    def _lock(self) -> None:
        self.state = SupervisorState.LOCKED
        self.mode = Mode.IDLE
        self._streamed = None
        self._segment = None

    @property
    def armed(self) -> bool:
        return self.state in (SupervisorState.READY, SupervisorState.FLYING, SupervisorState.LEVEL_OUT)

    @property
    def motors_on(self) -> bool:
        return self.state in (SupervisorState.FLYING, SupervisorState.LEVEL_OUT) and self.mode is not Mode.IDLE

    def supervisor_info(self) -> int:
        s = self.state
        bits = 1 << BIT_AUTO_ARMED
        if s is SupervisorState.DISARMED:
            bits |= 1 << BIT_CAN_BE_ARMED
        if self.armed:
            bits |= (1 << BIT_IS_ARMED) | (1 << BIT_CAN_FLY)
        if s in (SupervisorState.FLYING, SupervisorState.LEVEL_OUT):
            bits |= 1 << BIT_IS_FLYING
        if s is SupervisorState.LOCKED:
            bits |= 1 << BIT_IS_LOCKED
        if self.mode is Mode.HIGH_LEVEL:
            bits |= 1 << BIT_HL_ACTIVE
            if self._segment is not None and self._segment.finished(self._last_now):
                bits |= 1 << BIT_HL_FINISHED
        else:
            bits |= 1 << BIT_HL_DISABLED
        return bits

    _last_now = 0.0

    # ---- the control step -------------------------------------------------------------------------

    def control(self, now: float, pos: np.ndarray, vel: np.ndarray,
                yaw_deg: float) -> tuple[np.ndarray, float, bool]:
        """Desired velocity [m/s], yaw rate [deg/s] and motors-on for this instant; runs the watchdogs."""
        self._last_now = now
        if self._estop_deadline is not None and now > self._estop_deadline:
            logger.info("emergency-stop watchdog expired")
            self._estop_deadline = None
            self._lock()
        self._run_setpoint_watchdog(now, pos)
        if self.state in (SupervisorState.FLYING, SupervisorState.LEVEL_OUT) and self.mode is Mode.IDLE:
            if pos[2] <= self.params.ground_z + 1e-3 and abs(vel[2]) < 1e-3:
                self.state = SupervisorState.READY  # motors were cut and the drone is down
        if not self.motors_on:
            return np.zeros(3), 0.0, False
        kp = self.params.kp_pos
        if self.state is SupervisorState.LEVEL_OUT:
            return np.array([0.0, 0.0, kp * (self._hold_z - pos[2])]), 0.0, True
        if self.mode is Mode.HIGH_LEVEL:
            return self._control_high_level(now, pos, yaw_deg)
        t = self._streamed.target
        if self.mode is Mode.POSITION:
            return kp * (np.array(t[:3]) - pos), kp * _wrap_deg(t[3] - yaw_deg), True
        if self.mode is Mode.VELOCITY:
            return np.array(t[:3]), t[3], True
        # HOVER: body-frame horizontal velocity, absolute height
        c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        return np.array([c * t[0] - s * t[1], s * t[0] + c * t[1], kp * (t[3] - pos[2])]), t[2], True

    def _run_setpoint_watchdog(self, now: float, pos: np.ndarray) -> None:
        if self._streamed is None or self.mode is Mode.HIGH_LEVEL:
            return
        if self.state not in (SupervisorState.FLYING, SupervisorState.LEVEL_OUT):
            return
        age = now - self._streamed.stamp
        if age > WDT_SHUTDOWN_S:
            logger.info("setpoint watchdog: no setpoint for %.1f s, motors off, locked", age)
            self._lock()
        elif age > WDT_WARNING_S and self.state is SupervisorState.FLYING:
            logger.info("setpoint watchdog: no setpoint for %.1f s, levelling out", age)
            self.state = SupervisorState.LEVEL_OUT
            self._hold_z = float(pos[2])

    def _control_high_level(self, now: float, pos: np.ndarray, yaw_deg: float) -> tuple[np.ndarray, float, bool]:
        seg = self._segment
        ref_p, ref_v = seg.sample(now)
        if seg.finished(now) and self._landing and seg.end[2] <= self.params.ground_z + LANDED_HEIGHT_M:
            self.mode = Mode.IDLE
            self._segment = None
            self._landing = False
            # The motors stop; the supervisor reports "ready" (landed) once the drone rests on the floor.
            return np.zeros(3), 0.0, False
        yaw0, yaw1 = self._segment_yaw
        frac = 1.0 if seg.duration <= 0 else min(max((now - seg.t0) / seg.duration, 0.0), 1.0)
        yaw_ref = yaw0 + _wrap_deg(yaw1 - yaw0) * frac
        # Velocity and acceleration feed-forward from the planner, as the firmware's controllers use them:
        # with the first-order velocity response (tau) this tracks the trajectory without lagging behind it.
        ff = ref_v + self.params.tau * seg.acceleration(now)
        return ff + self.params.kp_pos * (ref_p - pos), self.params.kp_pos * _wrap_deg(yaw_ref - yaw_deg), True


def _wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0
