"""What the Crazyflie firmware does with the commands it receives: the commander's one setpoint and its
priority, the high-level commander's planner, the supervisor's state machine with its watchdogs, the
emergency stops. One ``Firmware`` per simulated drone; no sockets, no clocks (every call takes ``now`` [s]).

Followed from bitcraze/crazyflie-firmware (``src/modules/src/``):

* ``commander.c``: one setpoint slot with a priority (disable 0 < high level 1 < CRTP 2). A setpoint is taken
  when its priority is at least the current one and gets a fresh timestamp; a streamed (CRTP) setpoint stops
  the high-level planner. ``commanderRelaxPriority`` (the notify-setpoint-stop meta command,
  ``crtp_commander_generic.c``, whose remain-valid argument current firmware ignores) drops the priority to
  the lowest so that the planner's next setpoint is taken.
* ``crtp_commander_high_level.c`` / ``planner.c`` / ``stabilizer.c``: every control step, while the
  supervisor allows flight, the planner offers a setpoint at high-level priority: its trajectory while flying
  or landing, the *null setpoint* (motors off) while idle. Takeoff is refused unless the planner is idle, land
  while it is already landing; a finished landing makes it idle (so the motors stop). While flight is not
  allowed the planner is blocked (stopped, commands refused).
* ``supervisor.c`` / ``supervisor_state_machine.c``: ready -> flying once the motors run; flying -> warning
  level-out when the setpoint is older than 0.5 s (x, y control off, roll and pitch level, z as the setpoint
  had it: the drone coasts), back when a fresh one arrives; flying or level-out -> locked when it is older
  than 2 s or on an emergency stop (including the emergency-stop watchdog, 1 s); flying -> landed 2 s after
  the motors went idle; landed -> reset (and back to ready, or locked on a pending emergency stop) after 3 s.
"""
from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

import numpy as np

from groundstation.cf_firmware import (ESTOP_WATCHDOG_S, IS_FLYING_HYSTERESIS_S, LANDING_TIMEOUT_S, WDT_SHUTDOWN_S,
                                       WDT_WARNING_S)
from groundstation.sim.flight_model import QuadParams, Segment

logger = logging.getLogger(__name__)

EXTPOS_FRESH_S = 0.5
"""External positions younger than this dominate the position estimate [s]."""

PRIORITY_DISABLE, PRIORITY_HIGHLEVEL, PRIORITY_CRTP = 0, 1, 2
"""COMMANDER_PRIORITY_* (``src/modules/interface/commander.h``)."""


class SupervisorState(enum.Enum):
    DISARMED = "disarmed"
    READY = "ready"
    FLYING = "flying"
    LEVEL_OUT = "level_out"
    LANDED = "landed"
    LOCKED = "locked"


class Mode(enum.Enum):
    NULL = "null"
    """The null setpoint: every mode disabled, thrust zero (motors off)."""
    POSITION = "position"
    VELOCITY = "velocity"
    HOVER = "hover"
    TRAJECTORY = "trajectory"
    """A high-level-commander setpoint (position, velocity and acceleration of the planned trajectory)."""


class Planner(enum.Enum):
    IDLE = "idle"
    FLYING = "flying"
    LANDING = "landing"


# supervisor.info bits (crazyflie-firmware supervisor.c updateLogData, cflib supervisor.py)
BIT_CAN_BE_ARMED, BIT_IS_ARMED, BIT_AUTO_ARMED, BIT_CAN_FLY, BIT_IS_FLYING = 0, 1, 2, 3, 4
BIT_IS_LOCKED, BIT_HL_ACTIVE, BIT_HL_FINISHED, BIT_HL_DISABLED = 6, 8, 9, 10

_CAN_FLY = (SupervisorState.READY, SupervisorState.FLYING, SupervisorState.LEVEL_OUT, SupervisorState.LANDED)
"""supervisorCanFly / supervisorAreMotorsAllowedToRun (arming is instantaneous here)."""


@dataclass
class Setpoint:
    mode: Mode
    target: tuple[float, ...] = ()
    """POSITION (x, y, z, yaw_deg); VELOCITY (vx, vy, vz, yaw_rate_deg); HOVER (vx_body, vy_body,
    yaw_rate_deg, z); TRAJECTORY (x, y, z, vx, vy, vz, ax, ay, az, yaw_deg)."""
    stamp: float = -math.inf
    """When the commander took it [s]."""


NULL = Setpoint(Mode.NULL)


class Firmware:
    """Onboard logic of one drone."""

    def __init__(self, params: QuadParams, now: float) -> None:
        self.params = params
        self.state = SupervisorState.READY  # auto-arming, as on a stock Crazyflie 2.x
        self.group_mask = 0
        self.setpoint = Setpoint(Mode.NULL, (), now)  # commanderInit: the null setpoint
        self.priority = PRIORITY_DISABLE
        self.planner = Planner.IDLE  # plan_init
        self._segment: Segment | None = None
        self._segment_yaw = (0.0, 0.0)
        self._estop_requested = False
        self._estop_notified: float | None = None
        self._thrust_t = -math.inf
        self._landed_t = -math.inf
        self._extpos_time = -math.inf
        self.extpos = np.zeros(3)
        self._last_now = now

    # ---- the commander (commander.c) -----------------------------------------------------------------

    def _commander_set(self, now: float, sp: Setpoint, priority: int) -> None:
        if priority < self.priority:
            return
        sp.stamp = now
        self.setpoint, self.priority = sp, priority
        if priority > PRIORITY_HIGHLEVEL:
            self._planner_stop()  # "Stop the high-level planner so it will forget its current state"

    def stream(self, now: float, mode: Mode, target: tuple[float, ...]) -> None:
        """A streamed setpoint (generic or legacy commander port, CRTP priority)."""
        self._commander_set(now, Setpoint(mode, tuple(target)), PRIORITY_CRTP)

    def stream_stop(self, now: float) -> None:
        """The stop setpoint (type 0) or a zero-thrust legacy setpoint: the null setpoint at CRTP priority."""
        self._commander_set(now, Setpoint(Mode.NULL), PRIORITY_CRTP)

    def notify_setpoint_stop(self, now: float) -> None:
        """commanderRelaxPriority: any setpoint, the planner's included, may now replace the current one."""
        self.priority = PRIORITY_HIGHLEVEL

    # ---- the high-level commander (crtp_commander_high_level.c, planner.c) ----------------------------

    def _in_group(self, group_mask: int) -> bool:
        return group_mask == 0 or (group_mask & self.group_mask) != 0

    @property
    def _blocked(self) -> bool:
        return self.state not in _CAN_FLY  # crtpCommanderBlock(!supervisorCanFly())

    def _planner_stop(self) -> None:
        self.planner = Planner.IDLE  # plan_stop keeps the trajectory (its "finished" bit stays meaningful)

    def _reference(self, now: float, pos: np.ndarray) -> np.ndarray:
        """Where the planner plans from: its own trajectory when on one, else the state estimate."""
        if self.planner is not Planner.IDLE and self._segment is not None:
            return self._segment.sample(now)[0]
        return np.asarray(pos, dtype=float)

    def _plan(self, now, start, end, duration, yaw0, yaw1, linear=False) -> None:
        self._segment = Segment(now, max(float(duration), 0.0), tuple(float(s) for s in start),
                                tuple(float(e) for e in end), linear)
        self._segment_yaw = (yaw0, yaw1)

    def hl_takeoff(self, now: float, group_mask: int, pos: np.ndarray, yaw_deg: float, height: float,
                   duration: float, target_yaw_deg: float | None) -> bool:
        if self._blocked or not self._in_group(group_mask):
            return False
        if self.planner is not Planner.IDLE:  # plan_takeoff: only from idle
            logger.info("takeoff refused: the planner is %s", self.planner.value)
            return False
        start = self._reference(now, pos)
        self._plan(now, start, (start[0], start[1], float(height)), duration, yaw_deg,
                   yaw_deg if target_yaw_deg is None else target_yaw_deg)
        self.planner = Planner.FLYING
        return True

    def hl_land(self, now: float, group_mask: int, pos: np.ndarray, yaw_deg: float, height: float,
                duration: float, target_yaw_deg: float | None) -> bool:
        if self._blocked or not self._in_group(group_mask):
            return False
        if self.planner is Planner.LANDING:  # plan_land: not twice
            return False
        start = self._reference(now, pos)
        self._plan(now, start, (start[0], start[1], float(height)), duration, yaw_deg,
                   yaw_deg if target_yaw_deg is None else target_yaw_deg)
        self.planner = Planner.LANDING
        return True

    def hl_go_to(self, now: float, group_mask: int, pos: np.ndarray, yaw_deg: float,
                 goal: tuple[float, float, float], goal_yaw_deg: float, duration: float, relative: bool,
                 linear: bool) -> bool:
        if self._blocked or not self._in_group(group_mask):
            return False
        start = self._reference(now, pos)
        end = tuple(float(g) for g in goal)
        if relative:
            end = (start[0] + end[0], start[1] + end[1], start[2] + end[2])
            goal_yaw_deg += yaw_deg
        self._plan(now, start, end, duration, yaw_deg, goal_yaw_deg, linear)
        self.planner = Planner.FLYING
        return True

    def hl_stop(self, now: float, group_mask: int) -> None:
        if self._in_group(group_mask):
            self._planner_stop()  # idle: the planner now offers the null setpoint

    def _planner_setpoint(self, now: float) -> Setpoint:
        """crtpCommanderHighLevelGetSetpoint: the trajectory, or the null setpoint while idle."""
        seg = self._segment
        if self.planner is Planner.IDLE or seg is None:
            return Setpoint(Mode.NULL)
        if self.planner is Planner.LANDING and seg.finished(now):
            self._planner_stop()  # plan_current_goal: a finished landing goes idle (this step still flies it)
        p, v = seg.sample(now)
        a = seg.acceleration(now)
        yaw0, yaw1 = self._segment_yaw
        frac = 1.0 if seg.duration <= 0 else min(max((now - seg.t0) / seg.duration, 0.0), 1.0)
        return Setpoint(Mode.TRAJECTORY, (*p, *v, *a, yaw0 + _wrap_deg(yaw1 - yaw0) * frac))

    # ---- supervisor, localization ---------------------------------------------------------------------

    def emergency_stop(self, now: float) -> None:
        """crtpSupervisorSetEmergencyStop (or the stabilizer.stop parameter): locks at the next step."""
        self._estop_requested = True

    def emergency_stop_watchdog(self, now: float) -> None:
        """crtpSupervisorNotifyEmergencyStopWatchdog: arms the watchdog (until reboot) and feeds it."""
        self._estop_notified = now

    def crash(self, now: float, why: str) -> None:
        """A collision: the simulator cuts the motors and locks (the drone is broken until rebooted)."""
        self._lock(why)

    def arm(self, do_arm: bool) -> tuple[bool, bool]:
        """Supervisor arming request; returns (success, is_armed)."""
        if self.state is SupervisorState.LOCKED:
            return (not do_arm), False
        if do_arm and self.state is SupervisorState.DISARMED:
            self.state = SupervisorState.READY
        elif not do_arm and self.state in (SupervisorState.READY, SupervisorState.LANDED):
            self.state = SupervisorState.DISARMED
        elif not do_arm and self.state is not SupervisorState.DISARMED:
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

    def _lock(self, why: str) -> None:
        if self.state is not SupervisorState.LOCKED:
            logger.info("%s: motors off, locked (reboot required)", why)
        self.state = SupervisorState.LOCKED
        self._planner_stop()

    @property
    def watchdog_armed(self) -> bool:
        """A first emergency-stop-watchdog packet has arrived (it stays armed until reboot)."""
        return self._estop_notified is not None

    @property
    def armed(self) -> bool:
        return self.state in _CAN_FLY

    @property
    def motors_on(self) -> bool:
        return self._motors_on

    _motors_on = False

    @property
    def setpoint_age(self) -> float:
        return self._last_now - self.setpoint.stamp

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
        if self.planner is not Planner.IDLE:
            bits |= 1 << BIT_HL_ACTIVE  # TRAJECTORY_STATE_FLYING bit: flying or landing
        if self._segment is None or self._segment.finished(self._last_now):
            bits |= 1 << BIT_HL_FINISHED  # plan_is_finished: also with no trajectory yet
        return bits

    # ---- the control step (stabilizer.c) ---------------------------------------------------------------

    def control(self, now: float, pos: np.ndarray, vel: np.ndarray,
                yaw_deg: float) -> tuple[np.ndarray, float, bool, bool]:
        """One stabilizer step: the planner offers its setpoint, the supervisor judges, overrides, and the
        position controller runs. Returns desired velocity [m/s], yaw rate [deg/s], motors on, and whether
        horizontal control is off (level-out: the drone coasts)."""
        self._last_now = now
        if not self._blocked:
            self._commander_set(now, self._planner_setpoint(now), PRIORITY_HIGHLEVEL)
        else:
            self._planner_stop()
        self._supervise(now)
        sp = self.setpoint if self.state in _CAN_FLY else NULL
        self._motors_on = sp.mode is not Mode.NULL
        if self._motors_on:
            self._thrust_t = now
        else:
            return np.zeros(3), 0.0, False, False
        level_out = self.state is SupervisorState.LEVEL_OUT
        v, yaw_rate = self._track(sp, pos, yaw_deg)
        if level_out:
            return np.array([0.0, 0.0, v[2]]), 0.0, True, True  # roll, pitch level; yaw rate 0; z kept
        return v, yaw_rate, True, False

    def _supervise(self, now: float) -> None:
        """supervisorStateUpdate with this simulator's conditions (first matching transition wins)."""
        age = now - self.setpoint.stamp
        wdt_warning, wdt_timeout = age > WDT_WARNING_S, age > WDT_SHUTDOWN_S
        estop = self._estop_requested or (self._estop_notified is not None
                                          and now >= self._estop_notified + ESTOP_WATCHDOG_S)
        flying = now - self._thrust_t < IS_FLYING_HYSTERESIS_S
        s, S = self.state, SupervisorState
        if s is S.READY or s is S.DISARMED:
            if estop:
                self._lock("emergency stop" if self._estop_requested else "emergency-stop watchdog expired")
            elif s is S.READY and flying:
                self.state = S.FLYING
        elif s is S.FLYING or s is S.LEVEL_OUT:
            if wdt_timeout or estop:
                self._lock(f"setpoint watchdog: no setpoint for {age:.1f} s" if wdt_timeout
                           else "emergency-stop watchdog expired")
            elif s is S.FLYING and wdt_warning:
                logger.info("setpoint watchdog: no setpoint for %.2f s, levelling out", age)
                self.state = S.LEVEL_OUT
            elif s is S.LEVEL_OUT and not wdt_warning:
                self.state = S.FLYING
            elif s is S.FLYING and not flying:
                self.state, self._landed_t = S.LANDED, now
        elif s is S.LANDED:
            if now - self._landed_t > LANDING_TIMEOUT_S:
                # reset -> preflight checks -> (auto-)arming -> ready, unless an emergency stop is pending
                self.state = S.READY
                if estop:
                    self._lock("emergency-stop watchdog expired")
            elif flying:
                self.state = S.FLYING

    def _track(self, sp: Setpoint, pos: np.ndarray, yaw_deg: float) -> tuple[np.ndarray, float]:
        """The position controller as a desired velocity [m/s] and yaw rate [deg/s]."""
        kp, t = self.params.kp_pos, sp.target
        if sp.mode is Mode.POSITION:
            return kp * (np.array(t[:3]) - pos), kp * _wrap_deg(t[3] - yaw_deg)
        if sp.mode is Mode.VELOCITY:
            return np.array(t[:3]), t[3]
        if sp.mode is Mode.HOVER:  # body-frame horizontal velocity, absolute height
            c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
            return np.array([c * t[0] - s * t[1], s * t[0] + c * t[1], kp * (t[3] - pos[2])]), t[2]
        # TRAJECTORY: velocity and acceleration feed-forward from the planner, as the firmware's controllers
        # use them: with the first-order velocity response (tau) this tracks without lagging behind.
        ref_p, ref_v, ref_a = np.array(t[0:3]), np.array(t[3:6]), np.array(t[6:9])
        return ref_v + self.params.tau * ref_a + kp * (ref_p - pos), kp * _wrap_deg(t[9] - yaw_deg)


def _wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0
