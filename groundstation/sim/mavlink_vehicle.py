"""A simulated MAVLink 2 multicopter: a real protocol peer for ``MavlinkLink`` (pymavlink on both sides).

What it speaks (common dialect, one system, one component):

* sends ``HEARTBEAT`` (quadrotor; armed flag; system status STANDBY / ACTIVE / FLIGHT_TERMINATION),
  ``LOCAL_POSITION_NED`` (50 Hz), ``SYS_STATUS`` (battery voltage and remaining) and
  ``EXTENDED_SYS_STATE`` (landed state); rates change with ``MAV_CMD_SET_MESSAGE_INTERVAL``;
* ``COMMAND_LONG``: ``COMPONENT_ARM_DISARM`` (disarm in the air only with the force magic 21196),
  ``NAV_TAKEOFF`` (param7: height [m, up, above the local origin]), ``NAV_LAND`` (param7: landing height),
  ``DO_CHANGE_SPEED`` (speed types 0/1 horizontal, 2 climb, 3 descent), ``DO_FLIGHTTERMINATION`` (motors
  off, locked until ``PREFLIGHT_REBOOT_SHUTDOWN``), ``SET_MESSAGE_INTERVAL``; each answered by ``COMMAND_ACK``;
* ``SET_POSITION_TARGET_LOCAL_NED`` in ``MAV_FRAME_LOCAL_NED``: position targets when the type mask uses the
  position, else velocity targets; accepted only in the air. A velocity target older than
  ``setpoint_timeout`` (0.5 s) turns into a position hold where the drone is;
* fence upload with the mission protocol, ``mission_type = MAV_MISSION_TYPE_FENCE`` (the encoding is in
  ``groundstation.mavlink_link``): inclusion polygon, exclusion circles, ceiling. Leaving it in the air lands
  the vehicle (its own backstop behind the ground station's geofence);
* GCS heartbeat loss: armed and no ``HEARTBEAT`` from a GCS for ``gcs_timeout`` (1 s) -> land (on the ground:
  disarm).

Physics: ``groundstation.sim.flight_model.QuadBatch`` with one drone (the same first-order, speed- and
acceleration-limited, ground-contact model as the simulated Crazyflies), driven by a position controller
(desired velocity = ``kp_pos`` x error). The world frame is x east, y north, z up; the vehicle reports and
accepts NED (``ned_to_enu`` / ``enu_to_ned``).

>>> with MavlinkVehicle("udpout:127.0.0.1:14550") as vehicle:   # a ground station listens on 14550
...     ...
"""
from __future__ import annotations

import enum
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from groundstation.mavlink_link import (FORCE_DISARM_MAGIC, LOCAL_XY_SCALE, TYPE_MASK_IGNORE_POSITION,
                                        TYPE_MASK_IGNORE_VELOCITY, enu_to_ned, mavlink_module, ned_to_enu,
                                        open_mavlink)
from groundstation.sim.flight_model import QuadBatch, QuadParams

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class VehicleConfig:
    """Behaviour of the simulated vehicle."""

    system_id: int = 1
    component_id: int = 1
    heartbeat_period: float = 0.5
    """Seconds between two HEARTBEATs [s]."""
    position_rate: float = 50.0
    """Default LOCAL_POSITION_NED rate [Hz]."""
    status_rate: float = 5.0
    """Default SYS_STATUS and EXTENDED_SYS_STATE rate [Hz]."""
    physics_rate: float = 200.0
    """Simulation steps per second [Hz]."""
    gcs_timeout: float = 1.0
    """GCS heartbeat silence after which an armed vehicle lands [s]."""
    setpoint_timeout: float = 0.5
    """Age of a velocity setpoint after which the vehicle holds position [s]."""
    climb_speed: float = 0.5
    """Default takeoff climb speed [m/s]."""
    descent_speed: float = 0.4
    """Default landing descent speed [m/s]."""
    arrive_tolerance: float = 0.05
    """Takeoff is over within this distance of its height [m]."""
    max_step: float = 0.05
    """Longest physics step [s]: a thread that was descheduled longer loses time instead of jumping."""
    quad: QuadParams = field(default_factory=QuadParams)
    """Flight model (time constant, speed and acceleration limits, estimation noise, battery)."""


class VehicleMode(enum.Enum):
    DISARMED = 0
    IDLE = 1
    """Armed on the ground."""
    TAKEOFF = 2
    HOLD = 3
    """Holding a position (after takeoff, after a position setpoint, or when velocity setpoints stopped)."""
    VELOCITY = 4
    LAND = 5
    TERMINATED = 6
    """Flight terminated: motors off until rebooted."""


AIRBORNE = (VehicleMode.TAKEOFF, VehicleMode.HOLD, VehicleMode.VELOCITY)


@dataclass(frozen=True)
class VehicleFence:
    """The fence as uploaded (world frame)."""

    polygon: np.ndarray
    """[n, 2] inclusion corners [m]."""
    circles: tuple[tuple[float, float, float], ...]
    """Exclusion circles (x, y, radius) [m]."""
    z_max: float
    """Ceiling [m, up]; inf when none was given."""

    def contains(self, p: np.ndarray) -> bool:
        if p[2] > self.z_max:
            return False
        if any(math.hypot(p[0] - x, p[1] - y) < r for x, y, r in self.circles):
            return False
        if len(self.polygon) < 3:
            return True
        return _point_in_polygon(self.polygon, p[0], p[1])


def _point_in_polygon(poly: np.ndarray, x: float, y: float) -> bool:
    inside = False
    n = len(poly)
    for i in range(n):
        (x0, y0), (x1, y1) = poly[i], poly[(i + 1) % n]
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


class MavlinkVehicle:
    """One simulated vehicle on its own thread. ``start()`` / ``stop()`` or use as a context manager."""

    def __init__(self, connection: str, config: VehicleConfig | None = None,
                 start: tuple[float, float, float] = (0.0, 0.0, 0.0), seed: int = 0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.connection = connection
        self.config = config or VehicleConfig()
        self.clock = clock
        self._mav = mavlink_module()
        c = self.config
        self.quad = QuadBatch(1, c.quad, np.array([start], dtype=float), seed)
        self.mode = VehicleMode.DISARMED
        self.fence: VehicleFence | None = None
        self.fence_breaches = 0
        self.failsafe_landings = 0
        self.ignored_setpoints = 0
        self.setpoints_received = 0
        self.commands: list[tuple[int, int]] = []
        """(command, MAV_RESULT) of every COMMAND_LONG, in order."""
        self._target = np.array(start, dtype=float)
        self._vel_cmd = np.zeros(3)
        self._yaw_rate = 0.0
        self._setpoint_t = -math.inf
        self._land_height = c.quad.ground_z
        self._climb = c.climb_speed
        self._descent = c.descent_speed
        self._max_xy = c.quad.max_speed_xy
        self._last_gcs = -math.inf
        self._gcs_seen = False
        self._armed_at = -math.inf
        self._intervals = {
            self._mav.MAVLINK_MSG_ID_HEARTBEAT: c.heartbeat_period,
            self._mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1.0 / c.position_rate,
            self._mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0 / c.status_rate,
            self._mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0 / c.status_rate,
        }
        self._due: dict[int, float] = {k: 0.0 for k in self._intervals}
        self._rx: dict[str, Any] | None = None  # fence upload in progress
        self._t_boot = clock()
        self.link_alive = True
        """False after ``kill_link()``: the vehicle neither hears nor sends (a radio out of range)."""
        self._conn: Any = None
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
        logger.info("simulated MAVLink vehicle %d on %s", c.system_id, self.connection)
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
        """Go silent in both directions (a radio out of range); the vehicle flies on by itself and, missing
        the ground station's heartbeats, lands after ``gcs_timeout``."""
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
            dt = min(now - last, self.config.max_step)
            last = now
            with self.lock:
                if dt > 0:
                    self.step(dt, now)
                if self.link_alive:
                    self._send_due(now)
                    self._mission_retry(now)
            wait = period - (self.clock() - now)
            if wait > 0:
                try:
                    self._conn.select(wait)
                except (OSError, ValueError):
                    if self._stop.is_set():
                        return

    def step(self, dt: float, now: float) -> None:
        """Failsafes, controller and physics for ``dt`` [s] ending at ``now`` [s]."""
        c = self.config
        q = c.quad
        p = self.quad.pos[0]
        armed_ref = max(self._last_gcs, self._armed_at)
        if self.armed and now - armed_ref > c.gcs_timeout:
            if self.mode in AIRBORNE:
                logger.warning("vehicle %d: no GCS heartbeat for %.1f s: landing", c.system_id, now - armed_ref)
                self.failsafe_landings += 1
                self._start_land(q.ground_z)
            elif self.mode is VehicleMode.IDLE:
                logger.warning("vehicle %d: no GCS heartbeat on the ground: disarming", c.system_id)
                self._set_mode(VehicleMode.DISARMED)
        if self.fence is not None and self.mode in AIRBORNE and not self.fence.contains(p):
            logger.warning("vehicle %d: fence breached at (%.2f, %.2f, %.2f): landing", c.system_id, *p)
            self.fence_breaches += 1
            self._start_land(q.ground_z)
        if self.mode is VehicleMode.VELOCITY and now - self._setpoint_t > c.setpoint_timeout:
            logger.info("vehicle %d: velocity setpoints stopped: holding", c.system_id)
            self._target = p.copy()
            self._set_mode(VehicleMode.HOLD)

        v_des = np.zeros(3)
        motors = self.mode not in (VehicleMode.DISARMED, VehicleMode.TERMINATED)
        if self.mode in (VehicleMode.TAKEOFF, VehicleMode.HOLD):
            v_des = q.kp_pos * (self._target - p)
            if self.mode is VehicleMode.TAKEOFF:
                v_des[2] = min(max(v_des[2], -self._climb), self._climb)
                if abs(self._target[2] - p[2]) < c.arrive_tolerance:
                    self._set_mode(VehicleMode.HOLD)
        elif self.mode is VehicleMode.VELOCITY:
            v_des = self._vel_cmd.copy()
        elif self.mode is VehicleMode.LAND:
            v_des[:2] = q.kp_pos * (self._target[:2] - p[:2])
            v_des[2] = -self._descent
            if p[2] <= max(self._land_height, q.ground_z) + 0.02:
                logger.info("vehicle %d: landed at (%.2f, %.2f, %.2f): disarming", c.system_id, *p)
                self._set_mode(VehicleMode.DISARMED)
                motors = False
        hs = math.hypot(v_des[0], v_des[1])
        if hs > self._max_xy:
            v_des[:2] *= self._max_xy / hs
        self.quad.step(dt, v_des[None, :], np.array([math.degrees(self._yaw_rate)]), np.array([motors]))

    def _set_mode(self, mode: VehicleMode) -> None:
        if mode is not self.mode:
            logger.debug("vehicle %d: %s -> %s", self.config.system_id, self.mode.name, mode.name)
            self.mode = mode

    def _start_land(self, height: float) -> None:
        self._target = self.quad.pos[0].copy()
        self._land_height = height
        self._set_mode(VehicleMode.LAND)

    # ---- sending -----------------------------------------------------------------------------------

    def _send_due(self, now: float) -> None:
        for msg_id, interval in self._intervals.items():
            if interval is None or interval <= 0 or now < self._due[msg_id]:
                continue
            self._due[msg_id] = max(self._due[msg_id] + interval, now)
            self._send_message(msg_id, now)

    def _send_message(self, msg_id: int, now: float) -> None:
        mav, m = self._mav, self._conn.mav
        boot_ms = int((now - self._t_boot) * 1000) & 0xFFFFFFFF
        if msg_id == mav.MAVLINK_MSG_ID_HEARTBEAT:
            base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_GUIDED_ENABLED
            if self.armed:
                base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
            status = (mav.MAV_STATE_FLIGHT_TERMINATION if self.mode is VehicleMode.TERMINATED
                      else mav.MAV_STATE_ACTIVE if self.mode in AIRBORNE + (VehicleMode.LAND,)
                      else mav.MAV_STATE_STANDBY)
            m.heartbeat_send(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_GENERIC, base, self.mode.value, status)
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
            if msg.type == mav.MAV_TYPE_GCS:
                self._last_gcs = self.clock()
                if not self._gcs_seen:
                    self._gcs_seen = True
                    logger.info("vehicle %d: ground station %d connected", self.config.system_id,
                                msg.get_srcSystem())
            return
        target = getattr(msg, "target_system", None)
        if target not in (None, 0, self.config.system_id):
            return
        if kind == "COMMAND_LONG":
            result = self._command(msg)
            self.commands.append((msg.command, result))
            self._conn.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            self._setpoint(msg)
        elif kind in ("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_CLEAR_ALL"):
            self._mission(kind, msg)

    def _command(self, msg: Any) -> int:
        mav = self._mav
        cmd, p = msg.command, (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        ok, denied = mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_DENIED
        ground = self.config.quad.ground_z
        if cmd == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] >= 0.5:
                if self.mode is VehicleMode.TERMINATED:
                    return denied
                if self.mode is VehicleMode.DISARMED:
                    self._armed_at = self.clock()
                    self._target = self.quad.pos[0].copy()
                    self._set_mode(VehicleMode.IDLE)
                return ok
            if self.mode in AIRBORNE + (VehicleMode.LAND,) and p[1] != FORCE_DISARM_MAGIC:
                return denied
            if self.mode is not VehicleMode.TERMINATED:
                self._set_mode(VehicleMode.DISARMED)
            return ok
        if cmd == mav.MAV_CMD_NAV_TAKEOFF:
            if not self.armed or self.mode is VehicleMode.LAND:
                return denied
            height = p[6] if math.isfinite(p[6]) else 1.0
            if height <= ground + self.config.arrive_tolerance:
                return denied
            self._target = np.array([*self.quad.pos[0, :2], height])
            self._set_mode(VehicleMode.TAKEOFF)
            return ok
        if cmd == mav.MAV_CMD_NAV_LAND:
            if self.mode in AIRBORNE:
                self._start_land(p[6] if math.isfinite(p[6]) else ground)
            return ok
        if cmd == mav.MAV_CMD_DO_CHANGE_SPEED:
            speed = p[1]
            if not (math.isfinite(speed) and speed > 0):
                return ok if speed == -1 else denied
            kind = int(p[0])
            if kind == 2:
                self._climb = min(speed, self.config.quad.max_speed_z)
            elif kind == 3:
                self._descent = min(speed, self.config.quad.max_speed_z)
            elif kind in (0, 1):
                self._max_xy = min(speed, self.config.quad.max_speed_xy)
            else:
                return denied
            return ok
        if cmd == mav.MAV_CMD_DO_FLIGHTTERMINATION:
            if p[0] >= 0.5:
                logger.warning("vehicle %d: flight terminated", self.config.system_id)
                self._set_mode(VehicleMode.TERMINATED)
            return ok
        if cmd == mav.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            if p[0] != 1 or not self._on_ground():
                return denied
            self.reboot()
            return ok
        if cmd == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval_us = int(p[0]), p[1]
            if msg_id not in self._intervals:
                return mav.MAV_RESULT_UNSUPPORTED
            if interval_us == 0:  # default rate
                return ok
            self._intervals[msg_id] = None if interval_us < 0 else interval_us / 1e6
            return ok
        return mav.MAV_RESULT_UNSUPPORTED

    def reboot(self) -> None:
        """Back to disarmed with fresh defaults (clears a flight termination)."""
        c = self.config
        self._set_mode(VehicleMode.DISARMED)
        self._climb, self._descent, self._max_xy = c.climb_speed, c.descent_speed, c.quad.max_speed_xy
        self.quad.vel[:] = 0.0

    def _setpoint(self, msg: Any) -> None:
        self.setpoints_received += 1
        if msg.coordinate_frame != self._mav.MAV_FRAME_LOCAL_NED or self.mode not in AIRBORNE:
            self.ignored_setpoints += 1
            return
        mask = msg.type_mask
        if not mask & TYPE_MASK_IGNORE_POSITION:
            self._target = np.array(ned_to_enu(msg.x, msg.y, msg.z))
            self._yaw_rate = 0.0
            self._set_mode(VehicleMode.HOLD)
        elif not mask & TYPE_MASK_IGNORE_VELOCITY:
            self._vel_cmd = np.array(ned_to_enu(msg.vx, msg.vy, msg.vz))
            self._yaw_rate = -msg.yaw_rate if math.isfinite(msg.yaw_rate) else 0.0
            self._set_mode(VehicleMode.VELOCITY)
        else:
            self.ignored_setpoints += 1
            return
        self._setpoint_t = self.clock()

    # ---- fence upload (mission protocol, fence mission type) ---------------------------------------

    def _mission(self, kind: str, msg: Any) -> None:
        mav, m = self._mav, self._conn.mav
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        if msg.mission_type != mav.MAV_MISSION_TYPE_FENCE:
            m.mission_ack_send(src, comp, mav.MAV_MISSION_UNSUPPORTED, msg.mission_type)
            return
        if kind == "MISSION_CLEAR_ALL":
            self.fence, self._rx = None, None
            logger.info("vehicle %d: fence cleared", self.config.system_id)
            m.mission_ack_send(src, comp, mav.MAV_MISSION_ACCEPTED, msg.mission_type)
        elif kind == "MISSION_COUNT":
            if msg.count == 0:
                self.fence, self._rx = None, None
                m.mission_ack_send(src, comp, mav.MAV_MISSION_ACCEPTED, msg.mission_type)
                return
            self._rx = {"count": msg.count, "items": [], "src": src, "comp": comp, "t": self.clock(), "tries": 0}
            m.mission_request_int_send(src, comp, 0, msg.mission_type)
        elif kind == "MISSION_ITEM_INT":
            rx = self._rx
            if rx is None:
                return
            if msg.seq != len(rx["items"]):  # a repeat or out of order: ask again for the one we need
                m.mission_request_int_send(src, comp, len(rx["items"]), msg.mission_type)
                return
            rx["items"].append(msg)
            rx["t"], rx["tries"] = self.clock(), 0
            if len(rx["items"]) < rx["count"]:
                m.mission_request_int_send(src, comp, len(rx["items"]), msg.mission_type)
                return
            self._rx = None
            result = self._accept_fence(rx["items"])
            m.mission_ack_send(src, comp, result, msg.mission_type)

    def _mission_retry(self, now: float, after: float = 0.5, tries: int = 5) -> None:
        """Ask again for an item that did not come; give up (OPERATION_CANCELLED) after ``tries``."""
        rx, mav = self._rx, self._mav
        if rx is None or now - rx["t"] < after:
            return
        if rx["tries"] >= tries:
            logger.warning("vehicle %d: fence upload stalled at item %d of %d: cancelled", self.config.system_id,
                           len(rx["items"]), rx["count"])
            self._rx = None
            self._conn.mav.mission_ack_send(rx["src"], rx["comp"], mav.MAV_MISSION_OPERATION_CANCELLED,
                                            mav.MAV_MISSION_TYPE_FENCE)
            return
        rx["t"], rx["tries"] = now, rx["tries"] + 1
        self._conn.mav.mission_request_int_send(rx["src"], rx["comp"], len(rx["items"]), mav.MAV_MISSION_TYPE_FENCE)

    def _accept_fence(self, items: list[Any]) -> int:
        mav = self._mav
        poly: list[tuple[float, float]] = []
        circles: list[tuple[float, float, float]] = []
        z_max = math.inf
        for it in items:
            if it.frame != mav.MAV_FRAME_LOCAL_NED:
                return mav.MAV_MISSION_UNSUPPORTED_FRAME
            x, y, _ = ned_to_enu(it.x / LOCAL_XY_SCALE, it.y / LOCAL_XY_SCALE, 0.0)
            if it.command == mav.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION:
                poly.append((x, y))
                if it.z < 0:
                    z_max = min(z_max, -it.z)
            elif it.command == mav.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION:
                if not it.param1 > 0:
                    return mav.MAV_MISSION_INVALID_PARAM1
                circles.append((x, y, float(it.param1)))
            else:
                return mav.MAV_MISSION_UNSUPPORTED
        counts = {int(it.param1) for it in items if it.command == mav.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION}
        if poly and (len(poly) < 3 or counts != {len(poly)}):
            return mav.MAV_MISSION_INVALID_PARAM1
        self.fence = VehicleFence(np.array(poly, dtype=float).reshape(-1, 2), tuple(circles), z_max)
        logger.info("vehicle %d: fence with %d corners, %d exclusion circles, ceiling %.2f m",
                    self.config.system_id, len(poly), len(circles), z_max)
        return mav.MAV_MISSION_ACCEPTED
