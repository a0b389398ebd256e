"""Commands, mode changes, arming checks and setpoints of the simulated MAVLink vehicle, per firmware.

A mixin of ``groundstation.sim.mavlink_vehicle.MavlinkVehicle`` (it uses that class's state); the firmware rules
each method follows are cited where they apply:

* ArduCopter: ``ArduCopter/GCS_MAVLink_Copter.cpp`` (``handle_command_int_packet``, ``handle_MAV_CMD_NAV_TAKEOFF``,
  ``handle_MAV_CMD_DO_CHANGE_SPEED``, ``handle_message_set_position_target_local_ned``,
  ``handle_flight_termination``), ``ArduCopter/mode.h`` (``allows_arming``), ``libraries/GCS_MAVLink/GCS_Common.cpp``
  (``handle_command_component_arm_disarm``: results ``MAV_RESULT_FAILED`` on refusal).
* PX4: ``src/modules/commander/Commander.cpp`` (``handle_command``: arming and mode changes that fail are
  ``TEMPORARILY_REJECTED``), ``HealthAndArmingChecks/checks/offboardCheck.cpp`` (OFFBOARD needs a setpoint within
  ``COM_OF_LOSS_T``), ``src/modules/mavlink/mavlink_receiver.cpp`` (setpoints are the offboard proof of life in
  every mode and are flown only in OFFBOARD).
"""
from __future__ import annotations

import enum
import logging
import math
from typing import Any

import numpy as np

from groundstation.mavlink_autopilot import NOT_ARMABLE, mode_from_set_mode
from groundstation.mavlink_wire import FORCE_DISARM_MAGIC, TYPE_MASK_IGNORE_POSITION, TYPE_MASK_IGNORE_VELOCITY, \
    ned_to_enu

logger = logging.getLogger(__name__)


class VehicleMode(enum.Enum):
    """What the vehicle physically does (the autopilot's mode is ``MavlinkVehicle.flight_mode``)."""

    DISARMED = 0
    IDLE = 1
    """Armed on the ground."""
    TAKEOFF = 2
    HOLD = 3
    """Holding a position (after takeoff, a position setpoint, a mode change, or a stop)."""
    VELOCITY = 4
    LAND = 5
    TERMINATED = 6
    """Flight terminated (PX4): motors off until rebooted."""
    RTL = 7
    """Returning home at the return altitude (then LAND)."""


AIRBORNE = (VehicleMode.TAKEOFF, VehicleMode.HOLD, VehicleMode.VELOCITY, VehicleMode.RTL)



class AutopilotCommands:
    """COMMAND_LONG, SET_MODE and SET_POSITION_TARGET_LOCAL_NED handling (mixin of ``MavlinkVehicle``)."""

    _mav: Any
    px4: bool

    def _refused(self) -> int:
        return self._mav.MAV_RESULT_TEMPORARILY_REJECTED if self.px4 else self._mav.MAV_RESULT_FAILED

    def _command(self, msg: Any) -> int:
        mav = self._mav
        cmd, p = msg.command, (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        ok = mav.MAV_RESULT_ACCEPTED
        if cmd == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm(p[0] >= 0.5, p[1] == FORCE_DISARM_MAGIC)
        if cmd == mav.MAV_CMD_NAV_TAKEOFF:
            return self._takeoff(p[6])
        if cmd == mav.MAV_CMD_NAV_LAND:
            return self._set_mode("LAND")
        if cmd == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self._set_mode("RTL")
        if cmd == mav.MAV_CMD_DO_SET_MODE:
            return self._set_mode(mode_from_set_mode(self.autopilot, p[0], p[1], p[2]))
        if cmd == mav.MAV_CMD_DO_CHANGE_SPEED:
            return self._change_speed(int(p[0]), p[1])
        if cmd == mav.MAV_CMD_DO_FLIGHTTERMINATION:
            if not p[0] > 0.5:
                return mav.MAV_RESULT_FAILED
            logger.warning("vehicle %d: flight terminated", self.config.system_id)
            if self.px4:
                self.mode = VehicleMode.TERMINATED  # locked until rebooted
            else:
                self._disarm("flight termination")  # ArduCopter without AFS: a disarm
            return ok
        if cmd == mav.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            if p[0] != 1 or not self._on_ground():
                return mav.MAV_RESULT_DENIED
            self.reboot()
            return ok
        if cmd == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval_us = int(p[0]), p[1]
            if msg_id not in self._intervals:
                return mav.MAV_RESULT_UNSUPPORTED
            if interval_us != 0:  # 0: the default rate
                self._intervals[msg_id] = None if interval_us < 0 else interval_us / 1e6
                self._due[msg_id] = self.clock()  # the new rate starts now
            return ok
        if cmd == mav.MAV_CMD_REQUEST_MESSAGE:
            msg_id = int(p[0])
            if msg_id not in (mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, mav.MAVLINK_MSG_ID_HOME_POSITION,
                              *self._intervals):
                return mav.MAV_RESULT_UNSUPPORTED
            self._send_message(msg_id, self.clock())
            return ok
        return mav.MAV_RESULT_UNSUPPORTED

    # ---- arming ------------------------------------------------------------------------------------

    def _arm_problem(self) -> str | None:
        if self.mode is VehicleMode.TERMINATED:
            return "flight terminated: reboot first"
        if self.flight_mode in NOT_ARMABLE[self.autopilot]:
            return f"mode {self.flight_mode} not armable"
        if self.px4 and self.flight_mode == "OFFBOARD" and not self._offboard_signal():
            return "no offboard signal"
        if self._fence_on() and not self.fence.contains(self.quad.pos[0], self.fence_ceiling):
            return "vehicle outside fence"
        return None

    def _arm(self, arm: bool, forced: bool) -> int:
        mav = self._mav
        if arm:
            if self.armed:
                return mav.MAV_RESULT_ACCEPTED
            problem = self._arm_problem()
            if problem is not None:
                logger.warning("vehicle %d: arming refused: %s", self.config.system_id, problem)
                return mav.MAV_RESULT_DENIED if self.mode is VehicleMode.TERMINATED else self._refused()
            self._target = self.quad.pos[0].copy()
            self.mode = VehicleMode.IDLE
            if self.px4 and self.flight_mode == "TAKEOFF":  # a takeoff asked for while disarmed starts now
                self._start_takeoff(self._pending_takeoff)
            return mav.MAV_RESULT_ACCEPTED
        if self.mode is VehicleMode.TERMINATED:
            return mav.MAV_RESULT_DENIED
        if (self.mode in AIRBORNE or self.mode is VehicleMode.LAND) and not forced:
            return self._refused()  # in the air only with the force magic
        if self.armed:
            self._disarm("commanded" + (" (forced)" if forced else ""))
        return mav.MAV_RESULT_ACCEPTED

    # ---- takeoff, modes, speed ---------------------------------------------------------------------

    def _takeoff(self, alt: float) -> int:
        mav = self._mav
        home_z = self.home[2]
        if self.px4:
            # param7 is AMSL; NaN: MIS_TAKEOFF_ALT above home
            height = alt - self.config.origin.alt if math.isfinite(alt) else home_z + self.params["MIS_TAKEOFF_ALT"]
            if self.mode in AIRBORNE or self.mode is VehicleMode.LAND or self.mode is VehicleMode.TERMINATED:
                return self._refused()
            self._pending_takeoff = height
            self.flight_mode = "TAKEOFF"
            if self.mode is VehicleMode.IDLE:
                self._start_takeoff(height)
            return mav.MAV_RESULT_ACCEPTED
        # ArduCopter: param7 is the altitude above home; only a mode with a user takeoff, armed, landed
        if self.flight_mode != "GUIDED" or self.mode is not VehicleMode.IDLE or not math.isfinite(alt):
            return mav.MAV_RESULT_FAILED
        if alt <= self.quad.pos[0, 2] - home_z + self.config.arrive_tolerance:
            return mav.MAV_RESULT_FAILED
        self._start_takeoff(home_z + alt)
        return mav.MAV_RESULT_ACCEPTED

    def _start_takeoff(self, height: float) -> None:
        if self._climb_set is None:
            up = self.params["MPC_TKO_SPEED"] if self.px4 else self.params["WPNAV_SPEED_UP"] / 100.0
            self._climb = min(up, self.config.quad.max_speed_z)
        self._target = np.array([*self.quad.pos[0, :2], height])
        self.mode = VehicleMode.TAKEOFF

    def _offboard_signal(self) -> bool:
        return self.clock() - self._stream_t <= self.params["COM_OF_LOSS_T"]

    def _set_mode(self, name: str | None) -> int:
        mav = self._mav
        if name is None:
            return self._refused()
        if self.mode is VehicleMode.TERMINATED:
            return mav.MAV_RESULT_DENIED
        if self.px4 and name == "OFFBOARD" and not self._offboard_signal():
            logger.warning("vehicle %d: OFFBOARD refused: no setpoint stream", self.config.system_id)
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        if self.px4 and name == "TAKEOFF":
            return self._takeoff(math.nan)
        self._enter_mode(name)
        return mav.MAV_RESULT_ACCEPTED

    def _change_speed(self, kind: int, speed: float) -> int:
        mav = self._mav
        if not (math.isfinite(speed) and speed > 0):
            return mav.MAV_RESULT_DENIED  # ArduCopter: "Target speed must be larger than zero"
        if not self.px4 and self.flight_mode not in ("GUIDED", "AUTO"):
            return mav.MAV_RESULT_FAILED  # only the navigating modes implement set_speed_*
        q = self.config.quad
        if kind == 2:
            self._climb = self._climb_set = min(speed, q.max_speed_z)
        elif kind == 3:
            self._descent = min(speed, q.max_speed_z)
        elif kind in (0, 1):
            self._max_xy = min(speed, q.max_speed_xy)
        else:
            return mav.MAV_RESULT_DENIED
        return mav.MAV_RESULT_ACCEPTED

    # ---- setpoints ---------------------------------------------------------------------------------

    def _setpoint(self, msg: Any) -> None:
        self.setpoints_received += 1
        self._stream_t = self.clock()  # PX4: every setpoint is the offboard proof of life
        flying_mode = "OFFBOARD" if self.px4 else "GUIDED"
        if self.flight_mode != flying_mode or self.mode not in AIRBORNE or self.mode is VehicleMode.RTL:
            self.ignored_setpoints += 1
            return
        mask = msg.type_mask
        if msg.coordinate_frame != self._mav.MAV_FRAME_LOCAL_NED:
            self._hold_instead()
            return
        if not mask & TYPE_MASK_IGNORE_POSITION and mask & TYPE_MASK_IGNORE_VELOCITY:
            self._target = np.array(ned_to_enu(msg.x, msg.y, msg.z))
            self._yaw_rate = 0.0
            self.mode = VehicleMode.HOLD
        elif mask & TYPE_MASK_IGNORE_POSITION and not mask & TYPE_MASK_IGNORE_VELOCITY:
            v = np.array(ned_to_enu(msg.vx, msg.vy, msg.vz))
            if not np.all(np.isfinite(v)) or np.any(np.abs(v) > 1000):  # sane_vel_or_acc_vector
                self._hold_instead()
                return
            self._vel_cmd = v
            self._yaw_rate = -msg.yaw_rate if math.isfinite(msg.yaw_rate) else 0.0
            self.mode = VehicleMode.VELOCITY
        else:
            self._hold_instead()
            return
        self._setpoint_t = self._stream_t

    def _hold_instead(self) -> None:
        """An unusable setpoint: ArduCopter re-inits guided (holds at the stopping point); PX4 holds too."""
        self.ignored_setpoints += 1
        self._target = self._stopping_point()
        self.mode = VehicleMode.HOLD
