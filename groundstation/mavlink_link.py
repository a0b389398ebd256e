"""``MavlinkLink``: a MAVLink 2 vehicle (PX4, ArduPilot, or ``groundstation.sim.mavlink_vehicle``) via pymavlink.

URIs (``mavlink:udpin:127.0.0.1:14550``, ...) and the ENU/NED frames: ``groundstation.mavlink_wire``; the
commands, takeoff, landing and the fence upload: ``groundstation.mavlink_ops``. This module holds the
connection, its receive thread, the telemetry and the setpoint stream.

Protocol: MAVLink 2, common dialect; the vehicle must be ArduPilot (ArduCopter) or PX4 (``MAV_AUTOPILOT`` in its
heartbeat), whose differences live in ``groundstation.mavlink_autopilot``. The link sends a GCS ``HEARTBEAT``
every ``heartbeat_period`` (0.25 s) from its own thread. On opening it waits for the vehicle's heartbeat, asks
for ``HEARTBEAT`` (5 Hz), ``LOCAL_POSITION_NED``, ``SYS_STATUS`` and ``EXTENDED_SYS_STATE`` streams with
``MAV_CMD_SET_MESSAGE_INTERVAL``, waits for the first full telemetry sample, asks for ``GPS_GLOBAL_ORIGIN``
(``MAV_CMD_REQUEST_MESSAGE``) and turns on the firmware's own GCS-loss failsafe with ``PARAM_SET`` (ArduCopter
``FS_GCS_ENABLE`` = land, ``FS_GCS_TIMEOUT``; PX4 ``NAV_DLL_ACT`` = land, ``COM_DL_LOSS_T``, ``COM_OBL_RC_ACT`` =
land), each confirmed by its ``PARAM_VALUE``: both ship with it off. So a vehicle that stops hearing this
ground station (``close()``, a dead radio, a killed process) lands by itself after ``gcs_failsafe_timeout``.
"""
from __future__ import annotations

import collections
import logging
import math
import threading
import time
from typing import Any

from groundstation.link import FlightState, LinkError, LinkStats, Telemetry
from groundstation.mavlink_autopilot import LANDING_MODES, Autopilot, GlobalOrigin, failsafe_params, mode_name
from groundstation.mavlink_ops import MavlinkOperations, _Pending
from groundstation.mavlink_wire import (FORCE_DISARM_MAGIC, POSITION_MASK, SCHEME, TYPE_MASK_IGNORE_POSITION,
                                        TYPE_MASK_IGNORE_VELOCITY, TYPE_MASK_IGNORE_YAW, TYPE_MASK_IGNORE_YAW_RATE,
                                        VELOCITY_MASK, enu_to_ned, mav_name, mavlink_module, ned_to_enu,
                                        open_mavlink, parse_uri, split_baud, yaw_enu_to_ned, yaw_ned_to_enu)
from groundstation.mavlink_worker import CommandWorker

__all__ = ["FORCE_DISARM_MAGIC", "POSITION_MASK", "SCHEME", "TYPE_MASK_IGNORE_POSITION", "TYPE_MASK_IGNORE_VELOCITY",
           "TYPE_MASK_IGNORE_YAW", "TYPE_MASK_IGNORE_YAW_RATE", "VELOCITY_MASK", "MavlinkLink", "enu_to_ned",
           "mav_name", "mavlink_module", "ned_to_enu", "open_mavlink", "parse_uri", "split_baud", "yaw_enu_to_ned",
           "yaw_ned_to_enu"]

logger = logging.getLogger(__name__)


class MavlinkLink(MavlinkOperations):
    """One ArduPilot or PX4 vehicle. Opening blocks until its heartbeat, a full telemetry sample, its EKF origin
    and its confirmation of the GCS-loss failsafe parameters arrived.

    >>> with MavlinkLink("mavlink:udpin:127.0.0.1:14550") as link:
    ...     link.takeoff(1.0, 2.0).result(timeout=10)
    """

    arms_on_takeoff = True  # ArduPilot and PX4 rest disarmed; takeoff() arms through the worker

    def __init__(self, uri: str, *, connect_timeout: float = 10.0, heartbeat_period: float = 0.25,
                 telemetry_rate: float = 50.0, period_ms: int | None = None, link_loss_timeout: float = 0.25,
                 ack_timeout: float = 0.5, retries: int = 3, source_system: int = 255, source_component: int = 190,
                 gcs_failsafe_timeout: float = 1.0, offboard_prestream: float = 0.3) -> None:
        """``period_ms``, when given, sets the telemetry period like ``CflibLink(period_ms=...)`` and overrides
        ``telemetry_rate`` [Hz]. ``gcs_failsafe_timeout`` [s]: the vehicle lands by itself after this much
        silence of this ground station. ``offboard_prestream`` [s]: how long PX4 gets setpoints before the
        switch to OFFBOARD is asked for."""
        super().__init__(uri)
        self.connection = parse_uri(uri)
        if period_ms is not None:
            if not 1 <= period_ms <= 10_000:
                raise LinkError(uri, f"period_ms must be in 1..10000, got {period_ms}",
                                "pass the telemetry period in milliseconds, e.g. period_ms=20")
            telemetry_rate = 1000.0 / period_ms
        for name, value in (("telemetry_rate", telemetry_rate), ("ack_timeout", ack_timeout),
                            ("gcs_failsafe_timeout", gcs_failsafe_timeout)):
            if not (math.isfinite(value) and value > 0):
                raise LinkError(uri, f"{name} must be a positive number, got {value}",
                                f"pass {name} as a positive number (seconds, or Hz for telemetry_rate)")
        self.heartbeat_period = heartbeat_period
        self.telemetry_rate = telemetry_rate
        self.link_loss_timeout = link_loss_timeout
        self.ack_timeout = ack_timeout
        self.retries = retries
        self.gcs_failsafe_timeout = gcs_failsafe_timeout
        self.offboard_prestream = offboard_prestream
        self.target_system: int | None = None
        self.target_component: int = 1
        self.autopilot: Autopilot | None = None
        self.origin: GlobalOrigin | None = None
        self._mav = mavlink_module()
        try:
            self._conn = open_mavlink(self.connection, source_system, source_component)
        except ModuleNotFoundError as exc:
            raise LinkError(uri, f"pymavlink is not installed ({exc.name})", "pip install 'swarmpursuit[mavlink]'") \
                from exc
        except (OSError, ValueError) as exc:
            raise LinkError(uri, f"cannot open {self.connection}: {exc}",
                            "check the host and port (is another program bound to it?)") from exc
        self._send_lock = threading.Lock()
        self._sent = 0
        self._received = 0
        self._closed = False
        self._stop = threading.Event()
        self._acks: dict[int, _Pending] = {}
        self._params: dict[str, _Pending] = {}
        self._upload: dict[str, Any] | None = None
        self._armed = False
        self._takeoff_under_way = False  # a takeoff the vehicle accepted, not yet ended (mavlink_ops.takeoff)
        self._terminated = False
        self._estopped = False  # latched by emergency_stop() until a reboot: ArduPilot's termination only disarms
        self._custom_mode = 0
        self._landed_state = self._mav.MAV_LANDED_STATE_UNDEFINED
        self._battery_v = math.nan
        self._last_heartbeat = -math.inf
        self._got_heartbeat = threading.Event()
        self._got_origin = threading.Event()
        self._want_offboard = False
        self._stream_since = -math.inf
        self._last_setpoint = -math.inf
        self._offboard_asked = -math.inf
        self._arrivals: collections.deque[float] = collections.deque(maxlen=max(2, int(2 * telemetry_rate)))
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name=f"mavlink-link {self.connection}", daemon=True)
        self._thread.start()
        self._worker = CommandWorker(f"mavlink-commands {self.connection}")
        try:
            self._connect(connect_timeout)
        except LinkError:
            self.close()
            raise

    def _connect(self, timeout: float) -> None:
        uri = self.uri
        if not self._got_heartbeat.wait(timeout):
            raise LinkError(uri, f"no vehicle heartbeat within {timeout:.1f} s",
                            "start the vehicle or simulator and check that it sends to this address "
                            "(udpin listens, udpout sends first)")
        if self.autopilot is None:
            raise LinkError(uri, f"the vehicle's autopilot (MAV_AUTOPILOT {self._heartbeat_autopilot}) is neither "
                                 "ArduPilot nor PX4", "fly it with ArduPilot or PX4 firmware")
        self._request_streams()
        self.wait_telemetry(timeout, lambda s: not math.isnan(s.battery))
        mav = self._mav
        self.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
        if not self._got_origin.wait(min(timeout, 2.0)):
            logger.warning("%s: the vehicle sent no GPS_GLOBAL_ORIGIN: fences and PX4 takeoffs need it (set the EKF "
                           "origin with SET_GPS_GLOBAL_ORIGIN)", uri)
        for name, value in failsafe_params(self.autopilot, self.gcs_failsafe_timeout):
            self.set_param(name, value)

    # ---- receive thread ----------------------------------------------------------------------------

    def _run(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_beat:
                self._send("heartbeat_send", self._mav.MAV_TYPE_GCS, self._mav.MAV_AUTOPILOT_INVALID, 0, 0,
                           self._mav.MAV_STATE_ACTIVE)
                next_beat = now + self.heartbeat_period
            try:
                msg = self._conn.recv_msg()
            except OSError as exc:
                if self._stop.is_set():
                    return
                logger.warning("%s: receive failed: %s", self.uri, exc)
                msg = None
            if msg is None:
                try:
                    self._conn.select(min(0.01, max(next_beat - time.monotonic(), 0.0)))
                except (OSError, ValueError):
                    if self._stop.is_set():
                        return
                continue
            self._received += 1
            try:
                self._handle(msg)
            except Exception:  # one malformed message must not stop the link
                logger.exception("%s: handling %s failed", self.uri, msg.get_type())

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        mav = self._mav
        if kind == "BAD_DATA":
            return
        src = msg.get_srcSystem()
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg, src)
            return
        if src != self.target_system:
            return
        if kind == "LOCAL_POSITION_NED":
            self._on_position(msg)
        elif kind == "SYS_STATUS":
            if msg.voltage_battery != 65535:
                self._battery_v = msg.voltage_battery / 1000.0
        elif kind == "EXTENDED_SYS_STATE":
            self._landed_state = msg.landed_state
        elif kind == "COMMAND_ACK":
            pending = self._acks.get(msg.command)
            if pending is not None:
                pending.result = msg.result
                pending.event.set()
        elif kind == "PARAM_VALUE":
            name = msg.param_id.decode() if isinstance(msg.param_id, bytes) else str(msg.param_id)
            pending = self._params.get(name.rstrip("\x00"))
            if pending is not None:
                pending.result = float(msg.param_value)
                pending.event.set()
        elif kind == "GPS_GLOBAL_ORIGIN":
            self.origin = GlobalOrigin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            self._got_origin.set()
        elif kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            self._on_mission_request(msg)
        elif kind == "MISSION_ACK":
            up = self._upload
            if up is not None and msg.mission_type == up["mission_type"]:
                up["result"] = msg.type
                up["done"].set()

    def _on_heartbeat(self, msg: Any, src: int) -> None:
        mav = self._mav
        if msg.type in (mav.MAV_TYPE_GCS, mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_TYPE_GIMBAL):
            return
        if self.target_system is None:
            self.target_system, self.target_component = src, msg.get_srcComponent()
            self._heartbeat_autopilot = msg.autopilot
            self.autopilot = Autopilot.from_heartbeat(msg.autopilot)
            logger.info("%s: vehicle %d/%d (autopilot %d, type %d)", self.uri, src, self.target_component,
                        msg.autopilot, msg.type)
        if src != self.target_system:
            return
        armed = bool(msg.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
        if self._armed and not armed:
            self._takeoff_under_way = False  # disarmed: whatever flight was under way is over
        self._armed = armed
        self._terminated = msg.system_status in (mav.MAV_STATE_FLIGHT_TERMINATION, mav.MAV_STATE_EMERGENCY)
        self._custom_mode = msg.custom_mode
        if self.mode in LANDING_MODES:
            self._want_offboard = False  # the vehicle brings itself down: never switch it back
        self._last_heartbeat = time.monotonic()
        self._got_heartbeat.set()

    def _on_position(self, msg: Any) -> None:
        now = time.monotonic()
        self._arrivals.append(now)
        self._publish(Telemetry(
            t=now,
            position=ned_to_enu(msg.x, msg.y, msg.z),
            velocity=ned_to_enu(msg.vx, msg.vy, msg.vz),
            battery=self._battery_v,
            link_quality=self._link_quality(now),
            flight_state=self.flight_state,
            vehicle_time_ms=int(msg.time_boot_ms),
            planner_active=self._landed_state in (self._mav.MAV_LANDED_STATE_TAKEOFF,
                                                  self._mav.MAV_LANDED_STATE_LANDING),
        ))

    def _link_quality(self, now: float) -> float:
        """Fraction of the requested ``LOCAL_POSITION_NED`` samples that arrived over the last second."""
        recent = sum(1 for t in self._arrivals if now - t <= 1.0)
        window = min(1.0, now - self._arrivals[0])
        return min(1.0, recent / (window * self.telemetry_rate + 1.0))

    @property
    def mode(self) -> str:
        """The vehicle's flight mode by pymavlink's name (``GUIDED``, ``OFFBOARD``, ``LAND``...)."""
        if self.autopilot is None:
            return "UNKNOWN"
        return mode_name(self.autopilot, self._custom_mode)

    @property
    def flight_state(self) -> FlightState:
        """From the heartbeat's armed flag and system status and ``EXTENDED_SYS_STATE.landed_state``."""
        mav = self._mav
        if self._terminated or (self._estopped and not self._armed):
            return FlightState.LOCKED
        if not self._armed:
            return FlightState.DISARMED
        if self._landed_state == mav.MAV_LANDED_STATE_ON_GROUND:
            return FlightState.LANDED
        if self._landed_state in (mav.MAV_LANDED_STATE_IN_AIR, mav.MAV_LANDED_STATE_TAKEOFF,
                                  mav.MAV_LANDED_STATE_LANDING):
            return FlightState.FLYING
        return FlightState.UNKNOWN

    @property
    def armed(self) -> bool:
        return self._armed

    @property
    def link_lost(self) -> bool:
        return super().link_lost or time.monotonic() - self._last_heartbeat > max(3.0, 4 * self.link_loss_timeout)

    @property
    def command_errors(self) -> list[str]:
        """Every background command job that failed (``takeoff``, ``land``, the OFFBOARD switch), oldest first."""
        return list(self._worker.errors)

    # ---- sending -----------------------------------------------------------------------------------

    def _send(self, method: str, *args: Any) -> None:
        with self._send_lock:  # pymavlink's packer (sequence numbers) is not thread-safe
            try:
                getattr(self._conn.mav, method)(*args)
                self._sent += 1
            except OSError as exc:
                logger.warning("%s: send failed: %s", self.uri, exc)

    def _check_open(self) -> None:
        if self._closed:
            raise LinkError(self.uri, "the link is closed", "open a new one with open_link(uri)")

    def _time_boot_ms(self) -> int:
        return int((time.monotonic() - self._t0) * 1000) & 0xFFFFFFFF

    # ---- setpoints ---------------------------------------------------------------------------------

    def send_velocity(self, vx: float, vy: float, vz: float, yaw_rate: float = 0.0) -> None:
        self._check_open()
        n, e, d = enu_to_ned(vx, vy, vz)
        self._send("set_position_target_local_ned_send", self._time_boot_ms(), self.target_system,
                   self.target_component, self._mav.MAV_FRAME_LOCAL_NED, VELOCITY_MASK, 0.0, 0.0, 0.0, n, e, d,
                   0.0, 0.0, 0.0, 0.0, -float(yaw_rate))
        self._streaming()

    def send_position(self, x: float, y: float, z: float, yaw: float = 0.0) -> None:
        self._check_open()
        n, e, d = enu_to_ned(x, y, z)
        self._send("set_position_target_local_ned_send", self._time_boot_ms(), self.target_system,
                   self.target_component, self._mav.MAV_FRAME_LOCAL_NED, POSITION_MASK, n, e, d, 0.0, 0.0, 0.0,
                   0.0, 0.0, 0.0, yaw_enu_to_ned(yaw), 0.0)
        self._streaming()

    def _streaming(self) -> None:
        """PX4 flies setpoints only in OFFBOARD, which it accepts only while they arrive: after a takeoff, once
        the stream has run ``offboard_prestream``, ask for OFFBOARD (on the worker, never waiting here)."""
        now = time.monotonic()
        if now - self._last_setpoint > 0.5:
            self._stream_since = now
        self._last_setpoint = now
        if not (self._want_offboard and self._armed and self.mode not in ("OFFBOARD", "TAKEOFF", *LANDING_MODES)):
            return
        if now - self._stream_since >= self.offboard_prestream and now - self._offboard_asked > 0.5:
            self._offboard_asked = now
            self._worker.submit("offboard", lambda: self.set_mode("OFFBOARD"))

    # ---- bookkeeping -------------------------------------------------------------------------------

    def stats(self) -> LinkStats:
        return LinkStats(self._sent, self._received, self._telemetry_count, self.telemetry_age(),
                         self.link_lost, self._opened_at)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        latest = self.telemetry()
        if latest is not None and latest.flight_state is FlightState.FLYING and not self.link_lost:
            logger.warning("%s: closing while flying; the vehicle will land by itself once it misses the ground "
                           "station's heartbeats. Land first.", self.uri)
        self._worker.close()
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)
        with self._send_lock:
            self._conn.close()
