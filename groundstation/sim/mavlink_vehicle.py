"""A simulated MAVLink 2 multicopter that behaves as ArduCopter (default) or PX4: a real protocol peer for
``MavlinkLink`` and for ordinary pymavlink scripts.

Both personalities (``VehicleConfig.autopilot``) send ``HEARTBEAT`` (``MAV_TYPE_QUADROTOR``, their autopilot id,
base mode flags, the custom mode of ``groundstation.mavlink_autopilot``), ``LOCAL_POSITION_NED`` (50 Hz),
``SYS_STATUS``, ``EXTENDED_SYS_STATE`` (landed state), ``GPS_GLOBAL_ORIGIN`` / ``HOME_POSITION`` on
``MAV_CMD_REQUEST_MESSAGE``; answer ``PARAM_SET`` / ``PARAM_REQUEST_READ`` with ``PARAM_VALUE`` (their own
parameter names, firmware defaults); take fences with the mission protocol (``groundstation.sim.mavlink_fence``);
answer every ``COMMAND_LONG`` with ``COMMAND_ACK``.

ArduCopter (sources cited at each rule): boots in STABILIZE; ``SET_MODE`` / ``MAV_CMD_DO_SET_MODE`` change the
mode (``SET_MODE`` acked with command id 11, as ``GCS_MAVLINK::handle_set_mode`` does); arming is refused in
modes that do not allow it (LAND, RTL: ``allows_arming`` in ``ArduCopter/mode.h``) and outside an enabled fence;
``SET_POSITION_TARGET_LOCAL_NED`` is ignored unless the mode is GUIDED
(``GCS_MAVLINK_Copter::handle_message_set_position_target_local_ned``); a velocity target older than
``GUID_TIMEOUT`` (3 s) becomes a stop (``ModeGuided``); ``MAV_CMD_NAV_TAKEOFF`` (param7: altitude above home
[m]) only in GUIDED, armed and landed, else ``MAV_RESULT_FAILED`` (``handle_MAV_CMD_NAV_TAKEOFF``);
``MAV_CMD_NAV_LAND`` switches to LAND, which descends at ``LAND_SPEED`` and disarms on touchdown; RTL climbs to
``RTL_ALT`` (kept ``FENCE_MARGIN`` under an enabled ceiling), flies home and lands; the GCS failsafe
(``FS_GCS_ENABLE``, ``FS_GCS_TIMEOUT``; ``ArduCopter/events.cpp``) starts once a GCS heartbeat was seen and,
when it fires, disarms a landed vehicle or takes its action (LAND after a 4 s pause, or RTL);
``MAV_CMD_DO_FLIGHTTERMINATION`` disarms (``GCS_MAVLINK_Copter::handle_flight_termination``).

PX4: boots in AUTO.LOITER (Hold); ``MAV_CMD_NAV_TAKEOFF`` switches to AUTO.TAKEOFF (param7: AMSL altitude, NaN:
``MIS_TAKEOFF_ALT`` above home) and holds (AUTO.LOITER) at the top; OFFBOARD is accepted only while setpoints
have been arriving (the last one within ``COM_OF_LOSS_T``: ``HealthAndArmingChecks/checks/offboardCheck.cpp``),
else ``TEMPORARILY_REJECTED``; setpoints fly the vehicle only in OFFBOARD; losing them there for
``COM_OF_LOSS_T`` takes ``COM_OBL_RC_ACT`` (no RC here, so 0 "position" holds); ``NAV_DLL_ACT`` after
``COM_DL_LOSS_T`` without a GCS heartbeat; AUTO.LAND disarms ``COM_DISARM_LAND`` after touchdown; flight
termination locks the vehicle until ``MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN``.

Physics: ``groundstation.sim.flight_model.QuadBatch`` with one drone, driven by a position controller (desired
velocity = ``kp_pos`` x error). World frame x east, y north, z up; NED on the wire.

>>> with MavlinkVehicle("udpout:127.0.0.1:14550") as vehicle:   # a ground station listens on 14550
...     ...
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np

from groundstation.mavlink_autopilot import (COPTER_MODES, PX4_MODES, Autopilot, GlobalOrigin, mode_from_set_mode,
                                             px4_custom_mode)
from groundstation.mavlink_wire import enu_to_ned, mavlink_module, open_mavlink
from groundstation.sim.flight_model import QuadBatch, QuadParams
from groundstation.sim.mavlink_commands import AIRBORNE, AutopilotCommands, VehicleMode
from groundstation.sim.mavlink_fence import FenceReceiver, VehicleFence
from groundstation.sim.mavlink_modes import LAND_PAUSE, VehicleModes

__all__ = ["ARDUPILOT_PARAMS", "LAND_PAUSE", "PX4_PARAMS", "MavlinkVehicle", "VehicleConfig", "VehicleMode"]

logger = logging.getLogger(__name__)

ARDUPILOT_PARAMS = {"FS_GCS_ENABLE": 0.0, "FS_GCS_TIMEOUT": 5.0, "GUID_TIMEOUT": 3.0, "LAND_SPEED": 50.0,
                    "WPNAV_SPEED_UP": 250.0, "RTL_ALT": 1500.0, "FENCE_ENABLE": 0.0, "FENCE_TYPE": 7.0,
                    "FENCE_ALT_MAX": 100.0, "FENCE_ACTION": 1.0, "FENCE_MARGIN": 2.0, "SYSID_MYGCS": 255.0}
"""ArduCopter parameter defaults the simulator uses (``ArduCopter/Parameters.cpp``; speeds in cm/s, RTL_ALT cm)."""
PX4_PARAMS = {"NAV_DLL_ACT": 0.0, "COM_DL_LOSS_T": 10.0, "COM_OF_LOSS_T": 1.0, "COM_OBL_RC_ACT": 0.0,
              "COM_DISARM_LAND": 2.0, "MIS_TAKEOFF_ALT": 2.5, "MPC_LAND_SPEED": 0.7, "MPC_TKO_SPEED": 1.5,
              "RTL_RETURN_ALT": 60.0, "GF_ACTION": 2.0, "GF_MAX_VER_DIST": 0.0}
"""PX4 parameter defaults the simulator uses (``commander_params.c``, ``navigator`` and ``mc_pos_control`` params)."""


@dataclass(frozen=True)
class VehicleConfig:
    """Behaviour of the simulated vehicle."""

    autopilot: Autopilot = Autopilot.ARDUPILOT
    """Which firmware it behaves as."""
    system_id: int = 1
    component_id: int = 1
    params: Mapping[str, float] = field(default_factory=dict)
    """Parameter values at boot, over the firmware defaults (``ARDUPILOT_PARAMS`` / ``PX4_PARAMS``)."""
    origin: GlobalOrigin = GlobalOrigin(-35.363261, 149.165230, 584.0)
    """EKF origin and home (ArduPilot SITL's default location)."""
    heartbeat_period: float = 1.0
    """Seconds between two HEARTBEATs [s] (both firmwares send 1 Hz)."""
    position_rate: float = 50.0
    """Default LOCAL_POSITION_NED rate [Hz]."""
    status_rate: float = 5.0
    """Default SYS_STATUS and EXTENDED_SYS_STATE rate [Hz]."""
    physics_rate: float = 200.0
    """Simulation steps per second [Hz]."""
    arrive_tolerance: float = 0.05
    """Takeoff is over within this distance of its height [m]."""
    max_step: float = 0.05
    """Longest physics step [s]: a thread that was descheduled longer catches up in steps of this length."""
    max_catch_up: float = 1.0
    """Longest gap it catches up [s]; beyond it, the vehicle loses the time (a stopped process, not a slow one)."""
    quad: QuadParams = field(default_factory=QuadParams)
    """Flight model (time constant, speed and acceleration limits, estimation noise, battery)."""


class MavlinkVehicle(VehicleModes, AutopilotCommands):
    """One simulated vehicle on its own thread. ``start()`` / ``stop()`` or use as a context manager."""

    def __init__(self, connection: str, config: VehicleConfig | None = None,
                 start: tuple[float, float, float] = (0.0, 0.0, 0.0), seed: int = 0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.connection = connection
        self.config = c = config or VehicleConfig()
        self.autopilot = Autopilot(c.autopilot)
        self.px4 = self.autopilot is Autopilot.PX4
        self.clock = clock
        self._mav = mavlink_module()
        self.params = dict(PX4_PARAMS if self.px4 else ARDUPILOT_PARAMS)
        self.params.update({k.upper(): float(v) for k, v in c.params.items()})
        self.quad = QuadBatch(1, c.quad, np.array([start], dtype=float), seed)
        self.home = np.array([start[0], start[1], c.quad.ground_z])
        self.mode = VehicleMode.DISARMED
        self.flight_mode = "LOITER" if self.px4 else "STABILIZE"
        self.fence_breaches = 0
        self.failsafe_landings = 0
        """Landings (or returns) the vehicle started by itself: GCS loss, offboard loss, fence."""
        self.ignored_setpoints = 0
        self.setpoints_received = 0
        self.commands: list[tuple[int, int]] = []
        """(command, MAV_RESULT) of every COMMAND_LONG, in order."""
        self._target = np.array(start, dtype=float)
        self._vel_cmd = np.zeros(3)
        self._yaw_rate = 0.0
        self._setpoint_t = -math.inf
        self._stream_t = -math.inf  # latest setpoint of any kind (PX4's offboard proof of life)
        self._climb = c.quad.max_speed_z
        self._climb_set: float | None = None  # by DO_CHANGE_SPEED, else the firmware's takeoff speed
        self._pending_takeoff = self.home[2] + self.params.get("MIS_TAKEOFF_ALT", 1.0)
        self._descent: float | None = None
        self._max_xy = c.quad.max_speed_xy
        self._land_pause_until = -math.inf
        self._landed_at: float | None = None
        self._last_gcs = -math.inf
        self._gcs_failsafe = False
        self._intervals = {
            self._mav.MAVLINK_MSG_ID_HEARTBEAT: c.heartbeat_period,
            self._mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1.0 / c.position_rate,
            self._mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0 / c.status_rate,
            self._mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0 / c.status_rate,
        }
        self._due: dict[int, float] = {k: 0.0 for k in self._intervals}
        self._t_boot = clock()
        self.link_alive = True
        """False after ``kill_link()``: the vehicle neither hears nor sends (a radio out of range)."""
        self._conn: Any = None
        self._fences = FenceReceiver(self._mav, lambda: self._conn.mav, c.origin, c.system_id, clock)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.lock = threading.Lock()
        """Held while the vehicle steps; take it to read a consistent state from another thread."""

    # ---- lifecycle ---------------------------------------------------------------------------------

    def start(self) -> "MavlinkVehicle":
        c = self.config
        self._conn = open_mavlink(self.connection, c.system_id, c.component_id)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"mavlink-vehicle {self.connection}", daemon=True)
        self._thread.start()
        logger.info("simulated %s vehicle %d on %s", self.autopilot.value, c.system_id, self.connection)
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> "MavlinkVehicle":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def kill_link(self) -> None:
        """Go silent in both directions (a radio out of range); the vehicle flies on by itself until its own
        failsafes act."""
        with self.lock:
            self.link_alive = False

    def restore_link(self) -> None:
        with self.lock:
            self.link_alive = True

    @property
    def local_port(self) -> int:
        """The UDP port the vehicle's socket is bound to."""
        return int(self._conn.port.getsockname()[1])

    # ---- state, world frame ------------------------------------------------------------------------

    @property
    def position(self) -> np.ndarray:
        """True position [m, x east, y north, z up]."""
        with self.lock:
            return self.quad.pos[0].copy()

    @property
    def velocity(self) -> np.ndarray:
        with self.lock:
            return self.quad.vel[0].copy()

    @property
    def armed(self) -> bool:
        return self.mode not in (VehicleMode.DISARMED, VehicleMode.TERMINATED)

    @property
    def fence(self) -> VehicleFence | None:
        return self._fences.fence

    @property
    def fence_ceiling(self) -> float:
        """The ceiling [m, up] the vehicle enforces (inf when off)."""
        p = self.params
        if self.px4:
            return self.home[2] + p["GF_MAX_VER_DIST"] if p["GF_MAX_VER_DIST"] > 0 else math.inf
        return self.home[2] + p["FENCE_ALT_MAX"] if p["FENCE_ENABLE"] and int(p["FENCE_TYPE"]) & 1 else math.inf

    def _fence_on(self) -> bool:
        return self.fence is not None and (self.params["GF_ACTION"] > 0 if self.px4 else
                                           self.params["FENCE_ENABLE"] > 0)

    def _on_ground(self) -> bool:
        return bool(self.quad.pos[0, 2] <= self.config.quad.ground_z + 0.01)

    # ---- loop --------------------------------------------------------------------------------------

    def _run(self) -> None:
        period = 1.0 / self.config.physics_rate
        last = self.clock()
        while not self._stop.is_set():
            while True:
                try:
                    msg = self._conn.recv_msg()
                except OSError as exc:
                    logger.warning("vehicle %d: receive failed: %s", self.config.system_id, exc)
                    msg = None
                if msg is None:
                    break
                with self.lock:
                    if not self.link_alive:
                        continue
                    try:
                        self._handle(msg)
                    except Exception:  # a malformed message must not stop the vehicle
                        logger.exception("vehicle %d: handling %s failed", self.config.system_id, msg.get_type())
            now = self.clock()
            with self.lock:
                # a busy machine deschedules this thread for tens of ms: catch up in short steps so that the
                # vehicle's flight keeps the pace of its (wall-clock) timers, as the firmware's loop does
                t = max(last, now - self.config.max_catch_up)
                while now - t > 1e-9:
                    dt = min(now - t, self.config.max_step)
                    t += dt
                    self.step(dt, t)
                last = now
                if self.link_alive:
                    self._send_due(now)
                    self._fences.retry(now)
            wait = period - (self.clock() - now)
            if wait > 0:
                try:
                    self._conn.select(wait)
                except (OSError, ValueError):
                    if self._stop.is_set():
                        return

    def step(self, dt: float, now: float) -> None:
        """Failsafes, controller and physics for ``dt`` [s] ending at ``now`` [s]."""
        self._failsafes(now)
        q = self.config.quad
        p = self.quad.pos[0]
        v_des = np.zeros(3)
        motors = self.armed
        if self.mode in (VehicleMode.TAKEOFF, VehicleMode.HOLD):
            v_des = q.kp_pos * (self._target - p)
            if self.mode is VehicleMode.TAKEOFF:
                v_des[2] = min(max(v_des[2], -self._climb), self._climb)
                if abs(self._target[2] - p[2]) < self.config.arrive_tolerance:
                    self._takeoff_done()
        elif self.mode is VehicleMode.VELOCITY:
            v_des = self._vel_cmd.copy()
        elif self.mode is VehicleMode.RTL:
            v_des = self._rtl_velocity(p)
        elif self.mode is VehicleMode.LAND:
            v_des[:2] = q.kp_pos * (self._target[:2] - p[:2])
            v_des[2] = 0.0 if now < self._land_pause_until else -self._land_speed()
        elif self.mode is VehicleMode.IDLE and self._landed_at is not None:
            # PX4 disarms COM_DISARM_LAND after the land detector fired
            if now - self._landed_at >= self.params["COM_DISARM_LAND"]:
                self._disarm("landed")
        if self.mode is VehicleMode.LAND and p[2] <= q.ground_z + 0.02:
            logger.info("vehicle %d: landed at (%.2f, %.2f, %.2f)", self.config.system_id, *p)
            if self.px4 and self.params["COM_DISARM_LAND"] > 0:
                self._landed_at = now
                self.mode = VehicleMode.IDLE
            else:
                self._disarm("landed")
            motors = self.armed
            v_des[:] = 0.0
        hs = math.hypot(v_des[0], v_des[1])
        if hs > self._max_xy:
            v_des[:2] *= self._max_xy / hs
        self.quad.step(dt, v_des[None, :], np.array([math.degrees(self._yaw_rate)]), np.array([motors]))

    def _land_speed(self) -> float:
        if self._descent is not None:
            return self._descent
        speed = self.params["MPC_LAND_SPEED"] if self.px4 else self.params["LAND_SPEED"] / 100.0
        return min(speed, self.config.quad.max_speed_z)

    def _rtl_velocity(self, p: np.ndarray) -> np.ndarray:
        """Climb to the return altitude, fly home, then land (ArduCopter ``mode_rtl.cpp`` / PX4 ``rtl.cpp``)."""
        q = self.config.quad
        v = np.zeros(3)
        if p[2] < self._target[2] - self.config.arrive_tolerance:
            v[2] = min(q.kp_pos * (self._target[2] - p[2]), self._climb)
            return v
        v = q.kp_pos * (self._target - p)
        if math.hypot(*(self._target[:2] - p[:2])) < self.config.arrive_tolerance:
            self._start_land(pause=False)
        return v

    def _takeoff_done(self) -> None:
        self.mode = VehicleMode.HOLD
        if self.px4:
            self.flight_mode = "LOITER"  # PX4 holds at the end of AUTO.TAKEOFF


    def reboot(self) -> None:
        """Back to disarmed with fresh defaults (clears a flight termination)."""
        self.mode = VehicleMode.DISARMED
        self.flight_mode = "LOITER" if self.px4 else "STABILIZE"
        self._climb, self._climb_set = self.config.quad.max_speed_z, None
        self._descent, self._max_xy = None, self.config.quad.max_speed_xy
        self.quad.vel[:] = 0.0

    # ---- sending -----------------------------------------------------------------------------------

    def _send_due(self, now: float) -> None:
        for msg_id, interval in self._intervals.items():
            if interval is None or interval <= 0 or now < self._due[msg_id]:
                continue
            self._due[msg_id] = max(self._due[msg_id] + interval, now)
            self._send_message(msg_id, now)

    def _heartbeat(self) -> tuple[int, int, int, int]:
        """(autopilot, base_mode, custom_mode, system_status) as each firmware reports them."""
        mav = self._mav
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        if self.px4:
            main, sub = PX4_MODES[self.flight_mode]
            status = (mav.MAV_STATE_FLIGHT_TERMINATION if self.mode is VehicleMode.TERMINATED
                      else mav.MAV_STATE_ACTIVE if self.armed else mav.MAV_STATE_STANDBY)
            if main in (4, 6):  # auto and offboard: mavutil.px4_map's auto_mode_flags
                base |= mav.MAV_MODE_FLAG_AUTO_ENABLED | mav.MAV_MODE_FLAG_GUIDED_ENABLED | \
                    mav.MAV_MODE_FLAG_STABILIZE_ENABLED
            return mav.MAV_AUTOPILOT_PX4, base, px4_custom_mode(main, sub), status
        # GCS_MAVLINK_Copter::base_mode() and vehicle_system_status()
        base |= mav.MAV_MODE_FLAG_STABILIZE_ENABLED | mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if self.flight_mode in ("GUIDED", "LOITER", "RTL", "LAND", "AUTO", "BRAKE", "POSHOLD"):
            base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        status = (mav.MAV_STATE_CRITICAL if self._gcs_failsafe and self.armed
                  else mav.MAV_STATE_STANDBY if self.mode in (VehicleMode.DISARMED, VehicleMode.IDLE)
                  else mav.MAV_STATE_ACTIVE)
        return mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base, COPTER_MODES[self.flight_mode], status

    def _send_message(self, msg_id: int, now: float) -> None:
        mav, m = self._mav, self._conn.mav
        boot_ms = int((now - self._t_boot) * 1000) & 0xFFFFFFFF
        if msg_id == mav.MAVLINK_MSG_ID_HEARTBEAT:
            autopilot, base, custom, status = self._heartbeat()
            m.heartbeat_send(mav.MAV_TYPE_QUADROTOR, autopilot, base, custom, status)
        elif msg_id == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            est = self.quad.estimated_position(0, extpos_fresh=False)
            vel = self.quad.estimated_velocity(0)
            m.local_position_ned_send(boot_ms, *enu_to_ned(*est), *enu_to_ned(*vel))
        elif msg_id == mav.MAVLINK_MSG_ID_SYS_STATUS:
            volts = self.quad.battery_voltage(0, self.armed)
            q = self.config.quad
            remaining = int(round(100 * self.quad.charge_as[0] / q.battery_capacity_as))
            m.sys_status_send(0, 0, 0, 0, int(volts * 1000), -1, remaining, 0, 0, 0, 0, 0, 0)
        elif msg_id == mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            m.extended_sys_state_send(mav.MAV_VTOL_STATE_UNDEFINED, self._landed_state())
        elif msg_id == mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            o = self.config.origin
            m.gps_global_origin_send(round(o.lat * 1e7), round(o.lon * 1e7), round(o.alt * 1000), 0)
        elif msg_id == mav.MAVLINK_MSG_ID_HOME_POSITION:
            o = self.config.origin
            n, e, d = enu_to_ned(*self.home)
            m.home_position_send(round(o.lat * 1e7), round(o.lon * 1e7), round(o.alt * 1000), n, e, d,
                                 [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)

    def _landed_state(self) -> int:
        mav = self._mav
        if self.mode is VehicleMode.TAKEOFF:
            return mav.MAV_LANDED_STATE_TAKEOFF
        if self.mode is VehicleMode.LAND:
            return mav.MAV_LANDED_STATE_LANDING
        if self.mode in AIRBORNE:
            return mav.MAV_LANDED_STATE_IN_AIR
        return mav.MAV_LANDED_STATE_ON_GROUND if self._on_ground() else mav.MAV_LANDED_STATE_IN_AIR

    # ---- receiving ---------------------------------------------------------------------------------

    def _handle(self, msg: Any) -> None:
        mav = self._mav
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            # both firmwares count only their own GCS (ArduPilot: SYSID_MYGCS; PX4: any GCS-type heartbeat)
            if msg.type == mav.MAV_TYPE_GCS and (self.px4 or msg.get_srcSystem() == int(self.params["SYSID_MYGCS"])):
                if not math.isfinite(self._last_gcs):
                    logger.info("vehicle %d: ground station %d connected", self.config.system_id,
                                msg.get_srcSystem())
                self._last_gcs = self.clock()
                self._gcs_failsafe = False
            return
        target = getattr(msg, "target_system", None)
        if target not in (None, 0, self.config.system_id):
            return
        if kind == "COMMAND_LONG":
            result = self._command(msg)
            self.commands.append((msg.command, result))
            self._conn.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        elif kind == "SET_MODE":
            name = mode_from_set_mode(self.autopilot, msg.base_mode, msg.custom_mode, 0) if not self.px4 else \
                mode_from_set_mode(self.autopilot, msg.base_mode, (msg.custom_mode >> 16) & 0xFF,
                                   (msg.custom_mode >> 24) & 0xFF)
            result = self._set_mode(name)
            # GCS_MAVLINK::handle_set_mode acks the message with its message id as the "command"
            self._conn.mav.command_ack_send(mav.MAVLINK_MSG_ID_SET_MODE, result, 0, 0, msg.get_srcSystem(),
                                            msg.get_srcComponent())
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            self._setpoint(msg)
        elif kind in ("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_CLEAR_ALL"):
            self._fences.handle(kind, msg)
        elif kind in ("PARAM_SET", "PARAM_REQUEST_READ"):
            self._param(kind, msg)

    def _param(self, kind: str, msg: Any) -> None:
        name = msg.param_id.decode() if isinstance(msg.param_id, bytes) else str(msg.param_id)
        name = name.rstrip("\x00")
        if name not in self.params:
            return  # both firmwares ignore a parameter they do not have: the sender's wait times out
        if kind == "PARAM_SET" and math.isfinite(msg.param_value):
            self.params[name] = float(msg.param_value)
            logger.info("vehicle %d: %s = %g", self.config.system_id, name, msg.param_value)
        index = list(self.params).index(name)
        self._conn.mav.param_value_send(name.encode(), self.params[name], self._mav.MAV_PARAM_TYPE_REAL32,
                                        len(self.params), index)
