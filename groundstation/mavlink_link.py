"""``MavlinkLink``: a MAVLink 2 vehicle (PX4, ArduPilot, or ``groundstation.sim.mavlink_vehicle``) via pymavlink.

URI: ``mavlink:<pymavlink connection string>``. Everything after ``mavlink:`` goes to
``pymavlink.mavutil.mavlink_connection`` unchanged, so the scheme never collides with cflib's ``udp://``:

==========================================  ======================================================
``mavlink:udpin:127.0.0.1:14550``           listen on UDP 14550 (where PX4 SITL and most autopilots send)
``mavlink:udpout:192.168.4.1:14555``        send to a vehicle that listens
``mavlink:tcp:127.0.0.1:5760``              TCP client (ArduPilot SITL)
``mavlink:/dev/ttyACM0,57600``              serial (a telemetry radio or USB) at 57600 baud (default 115200)
==========================================  ======================================================

Not ``udp://``: that is cflib's (``CflibLink``), so a Crazyflie simulator and a MAVLink vehicle can never be
mistaken for each other. The serial baud rate follows a comma, because pymavlink reads ``HOST:PORT`` as UDP.

Protocol: MAVLink 2, common dialect; the vehicle must be ArduPilot (ArduCopter) or PX4 (``MAV_AUTOPILOT`` in its
heartbeat), whose differences live in ``groundstation.mavlink_autopilot``. The link sends a GCS ``HEARTBEAT``
every ``heartbeat_period`` (0.25 s) from its own thread. On opening it waits for the vehicle's heartbeat, asks
for ``HEARTBEAT`` (5 Hz), ``LOCAL_POSITION_NED``, ``SYS_STATUS`` and ``EXTENDED_SYS_STATE`` streams with
``MAV_CMD_SET_MESSAGE_INTERVAL``, waits for the first full telemetry sample, asks for ``GPS_GLOBAL_ORIGIN``
(``MAV_CMD_REQUEST_MESSAGE``) and turns on the firmware's own GCS-loss failsafe with ``PARAM_SET`` (ArduCopter
``FS_GCS_ENABLE`` = land, ``FS_GCS_TIMEOUT``; PX4 ``NAV_DLL_ACT`` = land, ``COM_DL_LOSS_T``, ``COM_OBL_RC_ACT`` =
land), each confirmed by its ``PARAM_VALUE``: both ship with it off. So a vehicle that stops hearing this
ground station (``close()``, a dead radio, a killed process) lands by itself after ``gcs_failsafe_timeout``.

Frames. The ground station's world frame is ENU-like: x east, y north, z up, yaw counter-clockwise from x.
MAVLink's local frame is NED: x north, y east, z down, yaw clockwise from north. The link converts every
position, velocity and yaw in both directions (``enu_to_ned`` / ``ned_to_enu``, swap x and y, negate z;
``yaw_ned = pi/2 - yaw_enu``; ``yaw_rate_ned = -yaw_rate_enu``), so callers never see NED.

Commands. ``send_velocity`` / ``send_position`` stream ``SET_POSITION_TARGET_LOCAL_NED`` (type masks
``VELOCITY_MASK`` / ``POSITION_MASK``, frame ``MAV_FRAME_LOCAL_NED``); ArduCopter flies them only in GUIDED,
PX4 only in OFFBOARD. ``takeoff`` on ArduCopter sets GUIDED, arms, sets the climb speed
(``MAV_CMD_DO_CHANGE_SPEED`` type 2) and sends ``MAV_CMD_NAV_TAKEOFF`` (param7: height above home); on PX4 it
arms and sends ``MAV_CMD_NAV_TAKEOFF`` (param7: AMSL, from the EKF origin), and once setpoints have streamed
for ``offboard_prestream`` the link asks for OFFBOARD, which PX4 refuses without a stream. ``land`` sends
``MAV_CMD_NAV_LAND``: both switch to their LAND mode and disarm on the ground. The link never switches a vehicle
out of LAND or RTL, nor out of a mode its caller chose. ``emergency_stop`` sends ``MAV_CMD_DO_FLIGHTTERMINATION``
(PX4 locks; ArduCopter disarms, and the link refuses to fly it again until a reboot).

Nothing the flight supervisor calls waits for the vehicle: ``takeoff``, ``land`` and the OFFBOARD switch run
on the link's worker thread (``groundstation.mavlink_worker``) and return a ``concurrent.futures.Future``; each
step waits for its ``COMMAND_ACK`` (``ack_timeout``, ``retries``) and a refused or unanswered one fails the
future with a ``LinkError`` naming the command and the result, logged and kept in ``command_errors``. A land
overtakes a takeoff that hangs. ``command``, ``set_mode``, ``set_param``, ``arm``, ``disarm`` and
``upload_fence`` block: call them before the flight or from your own thread.

Fence upload (``upload_fence``): the way each firmware takes it (``groundstation.mavlink_autopilot.fence_items``
and ``fence_params``): the polygon and keep-out circles as mission items (``mission_type =
MAV_MISSION_TYPE_FENCE``: ``MISSION_COUNT`` -> ``MISSION_REQUEST_INT`` / ``MISSION_ITEM_INT`` per item ->
``MISSION_ACK``) in ``MAV_FRAME_GLOBAL_INT`` around the vehicle's EKF origin, then the ceiling and the breach
action as parameters (ArduCopter ``FENCE_*``, PX4 ``GF_*``). The vehicle gets the fence itself, without the
margin: it is the backstop behind the ground station's geofence, which keeps setpoints a margin inside.
"""
from __future__ import annotations

import collections
import concurrent.futures
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterable

from groundstation.link import FlightState, Link, LinkError, LinkStats, Telemetry
from groundstation.mavlink_autopilot import (COPTER_MODES, LANDING_MODES, PX4_MODES, Autopilot, GlobalOrigin,
                                             failsafe_params, fence_items, fence_params, mode_name, set_mode_params)
from groundstation.mavlink_worker import CommandWorker

if TYPE_CHECKING:
    from groundstation.safety import FenceConfig

logger = logging.getLogger(__name__)

SCHEME = "mavlink:"

VELOCITY_MASK = 0b0000_0101_1100_0111
"""``POSITION_TARGET_TYPEMASK``: ignore x, y, z, accelerations and yaw; use vx, vy, vz and yaw rate."""
POSITION_MASK = 0b0000_1001_1111_1000
"""``POSITION_TARGET_TYPEMASK``: ignore velocities, accelerations and yaw rate; use x, y, z and yaw."""
TYPE_MASK_IGNORE_POSITION = 0b111
TYPE_MASK_IGNORE_VELOCITY = 0b111000
TYPE_MASK_IGNORE_YAW = 1 << 10
TYPE_MASK_IGNORE_YAW_RATE = 1 << 11

FORCE_DISARM_MAGIC = 21196.0
"""param2 of ``MAV_CMD_COMPONENT_ARM_DISARM`` that forces a disarm in the air."""


# --------------------------------------------------------------------------------------------------
# frames


def enu_to_ned(x: float, y: float, z: float) -> tuple[float, float, float]:
    """World (x east, y north, z up) -> MAVLink local NED (north, east, down). Also for velocities."""
    return y, x, -z


def ned_to_enu(n: float, e: float, d: float) -> tuple[float, float, float]:
    """MAVLink local NED -> world (x east, y north, z up). Also for velocities."""
    return e, n, -d


def yaw_enu_to_ned(yaw: float) -> float:
    """[rad] counter-clockwise from east -> clockwise from north, wrapped to (-pi, pi]."""
    return _wrap(math.pi / 2 - yaw)


def yaw_ned_to_enu(yaw: float) -> float:
    return _wrap(math.pi / 2 - yaw)


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


# --------------------------------------------------------------------------------------------------
# pymavlink plumbing shared with the simulated vehicle


def mavlink_module() -> Any:
    """pymavlink's MAVLink 2 common dialect (imported lazily: pymavlink is the ``mavlink`` extra)."""
    from pymavlink.dialects.v20 import common
    return common


def open_mavlink(connection: str, source_system: int, source_component: int) -> Any:
    """A ``mavutil`` connection for ``connection`` that speaks MAVLink 2 with the common dialect.
    A serial device may carry its baud rate after a comma (``/dev/ttyACM0,57600``; default 115200).

    mavutil picks its dialect and wire version from the process-wide ``MAVLINK20`` environment variable; this
    sets the parser of this one connection instead, so other pymavlink users in the process are unaffected."""
    from pymavlink import mavutil
    mav = mavlink_module()
    device, baud = split_baud(connection)
    conn = mavutil.mavlink_connection(device, baud=baud, source_system=source_system,
                                      source_component=source_component)
    conn.mav = mav.MAVLink(conn, srcSystem=source_system, srcComponent=source_component)
    conn.mav.robust_parsing = True
    conn.WIRE_PROTOCOL_VERSION = "2.0"
    conn.first_byte = False  # no auto-switching of the global dialect on the first byte
    return conn


_NETWORK_KINDS = ("udpin", "udpout", "udp", "udpbcast", "tcp", "tcpin")


def split_baud(connection: str) -> tuple[str, int]:
    """``/dev/ttyACM0,57600`` -> (``/dev/ttyACM0``, 57600); anything without a baud -> (it, 115200)."""
    device, sep, baud = connection.rpartition(",")
    if sep and device and baud.isdigit() and connection.split(":", 1)[0] not in _NETWORK_KINDS:
        return device, int(baud)
    return connection, 115200


def parse_uri(uri: str) -> str:
    """``mavlink:udpin:127.0.0.1:14550`` -> ``udpin:127.0.0.1:14550``; ``LinkError`` for malformed URIs."""
    if not uri.lower().startswith(SCHEME):
        raise LinkError(uri, "not a MAVLink URI", "write it as mavlink:udpin:127.0.0.1:14550 (the part after "
                                                   "'mavlink:' is a pymavlink connection string)")
    rest = uri[len(SCHEME):]
    if not rest or rest.startswith("//"):
        raise LinkError(uri, "missing or malformed pymavlink connection string",
                        "write mavlink:udpin:HOST:PORT, mavlink:udpout:HOST:PORT, mavlink:tcp:HOST:PORT or "
                        "mavlink:/dev/ttyUSB0 (no '//' after 'mavlink:')")
    kind = rest.split(":", 1)[0]
    if kind in _NETWORK_KINDS and rest.count(":") != 2:
        raise LinkError(uri, f"{kind} needs HOST:PORT", f"write mavlink:{kind}:127.0.0.1:14550")
    if kind not in _NETWORK_KINDS and (rest.startswith("/") or rest.upper().startswith("COM")) and ":" in rest:
        # pymavlink would take DEVICE:BAUD for a UDP address
        raise LinkError(uri, "serial baud rate written after ':'",
                        f"write it after a comma: mavlink:{rest.replace(':', ',', 1)}")
    return rest


# --------------------------------------------------------------------------------------------------
# the link


@dataclass
class _Pending:
    event: threading.Event
    result: Any = None


class MavlinkLink(Link):
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
        self._armed = bool(msg.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
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

    def _wait(self, event: threading.Event, timeout: float, interruptible: bool) -> bool:
        """Wait for ``event``; in a worker job that was preempted, give up at once (``LinkError``)."""
        deadline = time.monotonic() + timeout
        while True:
            if event.wait(min(0.02, max(deadline - time.monotonic(), 0.0))):
                return True
            if interruptible and self._worker.should_stop():
                raise LinkError(self.uri, "command abandoned: a landing overtook it, or the link is closing",
                                "nothing to do: the landing (or the close) goes on")
            if time.monotonic() >= deadline:
                return False

    def command(self, command: int, *params: float, timeout: float | None = None) -> int:
        """Send ``COMMAND_LONG`` (up to 7 params) and wait for its ``COMMAND_ACK``; returns the ``MAV_RESULT``.
        Retried ``retries`` times (with the confirmation counter) when unanswered; ``LinkError`` then. Blocks:
        the flight supervisor's ``takeoff`` / ``land`` go through the link's worker instead."""
        self._check_open()
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        pending = _Pending(threading.Event())
        self._acks[command] = pending
        interruptible = threading.current_thread() is self._worker._thread
        try:
            for attempt in range(self.retries + 1):
                self._send("command_long_send", self.target_system, self.target_component, command, attempt, *p)
                if self._wait(pending.event, timeout or self.ack_timeout, interruptible):
                    if command == self._mav.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN and \
                            pending.result == self._mav.MAV_RESULT_ACCEPTED:
                        self._estopped = False
                    return int(pending.result)
        finally:
            self._acks.pop(command, None)
        raise LinkError(self.uri, f"command {_name(self._mav, 'MAV_CMD_', command)} unanswered after "
                                  f"{self.retries + 1} tries of {timeout or self.ack_timeout:.2f} s",
                        "check the link; the vehicle may not support this command")

    def _command_ok(self, command: int, what: str, *params: float) -> None:
        result = self.command(command, *params)
        if result != self._mav.MAV_RESULT_ACCEPTED:
            raise LinkError(self.uri, f"{what} refused: {_name(self._mav, 'MAV_RESULT_', result)} (mode {self.mode})",
                            "check the vehicle's state (armed, on the ground, not locked by a failsafe)")

    def set_param(self, name: str, value: float, timeout: float | None = None) -> float:
        """``PARAM_SET`` and wait for the vehicle's ``PARAM_VALUE`` echo; ``LinkError`` when it never comes
        (both firmwares stay silent about a parameter they do not have)."""
        self._check_open()
        pending = _Pending(threading.Event())
        self._params[name] = pending
        try:
            for _ in range(self.retries + 1):
                self._send("param_set_send", self.target_system, self.target_component, name.encode(), float(value),
                           self._mav.MAV_PARAM_TYPE_REAL32)
                if self._wait(pending.event, timeout or self.ack_timeout, False):
                    if not math.isclose(pending.result, value, rel_tol=1e-6, abs_tol=1e-6):
                        raise LinkError(self.uri, f"parameter {name} is {pending.result:g} after setting {value:g}",
                                        "check the parameter's range on this firmware")
                    return pending.result
        finally:
            self._params.pop(name, None)
        raise LinkError(self.uri, f"parameter {name} not confirmed by the vehicle",
                        f"check that this {self.autopilot.value if self.autopilot else ''} firmware has {name}")

    def set_mode(self, name: str) -> None:
        """Switch the flight mode (``MAV_CMD_DO_SET_MODE``); blocks for the ack, ``LinkError`` if refused."""
        try:
            params = set_mode_params(self.autopilot, name)
        except KeyError:
            raise LinkError(self.uri, f"unknown {self.autopilot.value} mode {name!r}",
                            "use one of " + ", ".join(PX4_MODES if self.autopilot is Autopilot.PX4 else COPTER_MODES))
        if name != "OFFBOARD":
            self._want_offboard = False  # a mode chosen by the caller is kept, not overridden by the stream
        self._command_ok(self._mav.MAV_CMD_DO_SET_MODE, f"mode {name}", *params)

    def _request_streams(self) -> None:
        mav = self._mav
        period_us = 1e6 / self.telemetry_rate
        # heartbeats at 5 Hz: the armed flag and the mode travel in them (both firmwares default to 1 Hz)
        for msg_id, interval in ((mav.MAVLINK_MSG_ID_HEARTBEAT, 2e5),
                                 (mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, period_us),
                                 (mav.MAVLINK_MSG_ID_SYS_STATUS, 2e5),
                                 (mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2e5)):
            result = self.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval)
            if result != mav.MAV_RESULT_ACCEPTED:
                logger.warning("%s: vehicle refused the stream rate of message %d (result %d); using its default",
                               self.uri, msg_id, result)

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

    # ---- takeoff, landing, stop (queued on the worker) ---------------------------------------------

    def _check_flyable(self) -> None:
        self._check_open()
        if self._terminated or self._estopped:
            raise LinkError(self.uri, "the vehicle is locked by a flight termination (emergency stop)",
                            "reboot it: link.command(MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)")

    def takeoff(self, height: float, duration: float) -> concurrent.futures.Future:
        """Queue the takeoff to ``height`` [m, world z] and return its future at once: ArduPilot GUIDED, arm,
        climb speed, ``NAV_TAKEOFF`` (param7 above home); PX4 arm, ``NAV_TAKEOFF`` (param7 AMSL from the EKF
        origin), then OFFBOARD once setpoints stream. ``LinkError`` now only for a closed or locked link; a
        refused step fails the future (and is logged, and kept in ``command_errors``)."""
        self._check_flyable()
        self._worker.preempt(("land",))
        return self._worker.submit("takeoff", lambda: self._takeoff(height, duration))

    def _takeoff(self, height: float, duration: float) -> None:
        mav = self._mav
        if self.autopilot is Autopilot.PX4:
            if self.origin is None:
                raise LinkError(self.uri, "PX4 takeoff needs the EKF origin (GPS_GLOBAL_ORIGIN)",
                                "set the vehicle's EKF origin before flying")
            if not self._armed:
                self._command_ok(mav.MAV_CMD_COMPONENT_ARM_DISARM, "arming", 1.0)
            self._want_offboard = True
            self._command_ok(mav.MAV_CMD_NAV_TAKEOFF, "takeoff", 0, 0, 0, math.nan, math.nan, math.nan,
                             self.origin.alt + height)
            return
        if self.mode != "GUIDED":
            self.set_mode("GUIDED")
        if not self._armed:
            self._command_ok(mav.MAV_CMD_COMPONENT_ARM_DISARM, "arming", 1.0)
        latest = self.telemetry()
        z0 = latest.position[2] if latest is not None else 0.0
        if duration > 0 and height > z0:
            result = self.command(mav.MAV_CMD_DO_CHANGE_SPEED, 2.0, (height - z0) / duration, -1.0)
            if result != mav.MAV_RESULT_ACCEPTED:
                logger.info("%s: climb speed not taken (%s); the firmware's takeoff speed applies", self.uri,
                            _name(mav, "MAV_RESULT_", result))
        self._command_ok(mav.MAV_CMD_NAV_TAKEOFF, "takeoff", 0, 0, 0, math.nan, math.nan, math.nan, height)

    def land(self, duration: float, height: float = 0.0) -> concurrent.futures.Future:
        """Queue ``MAV_CMD_NAV_LAND`` (both firmwares switch to their LAND mode, descend at their landing speed
        and disarm on the ground; ``duration`` and ``height`` are theirs to choose) and return its future.
        A queued or hanging takeoff is abandoned first. Repeated calls while one is in flight share it."""
        self._check_open()
        self._want_offboard = False
        self._worker.preempt(("takeoff", "offboard"))
        return self._worker.submit("land", lambda: self._command_ok(
            self._mav.MAV_CMD_NAV_LAND, "landing", 0, 0, 0, math.nan, math.nan, math.nan, 0.0))

    def arm(self) -> None:
        self._check_flyable()
        self._command_ok(self._mav.MAV_CMD_COMPONENT_ARM_DISARM, "arming", 1.0)

    def disarm(self, force: bool = False) -> None:
        """Disarm; vehicles refuse in the air unless ``force`` (then the motors stop and it falls)."""
        self._command_ok(self._mav.MAV_CMD_COMPONENT_ARM_DISARM, "disarming", 0.0,
                         FORCE_DISARM_MAGIC if force else 0.0)

    def emergency_stop(self) -> None:
        """``MAV_CMD_DO_FLIGHTTERMINATION``, sent three times without waiting (a lost packet must not delay
        it). PX4 locks until rebooted; ArduCopter disarms, and this link keeps it locked until a reboot."""
        self._check_open()
        self._estopped = True
        self._want_offboard = False
        for attempt in range(3):
            self._send("command_long_send", self.target_system, self.target_component,
                       self._mav.MAV_CMD_DO_FLIGHTTERMINATION, attempt, 1.0, 0, 0, 0, 0, 0, 0)

    # ---- fence -------------------------------------------------------------------------------------

    def upload_fence(self, fence: "FenceConfig", timeout: float = 5.0) -> int:
        """Give the vehicle ``fence`` the way its firmware takes it (``groundstation.mavlink_autopilot``):
        polygon and keep-out circles as fence mission items in the global frame, then the parameters for the
        ceiling and a landing on breach. Returns the item count; ``LinkError`` when refused or unfinished.
        Blocks: call it before the flight."""
        if self.origin is None:
            raise LinkError(self.uri, "no EKF origin (GPS_GLOBAL_ORIGIN) to place the fence",
                            "set the vehicle's EKF origin, then upload the fence")
        n = self._upload_items(fence_items(fence, self.origin), self._mav.MAV_MISSION_TYPE_FENCE, timeout)
        for name, value in fence_params(self.autopilot, fence):
            self.set_param(name, value)
        return n

    def clear_fence(self, timeout: float = 2.0) -> None:
        """Remove the vehicle's fence (``MISSION_CLEAR_ALL`` with the fence mission type)."""
        self._upload_items([], self._mav.MAV_MISSION_TYPE_FENCE, timeout, clear=True)
        if self.autopilot is Autopilot.ARDUPILOT:
            self.set_param("FENCE_ENABLE", 0.0)

    def _upload_items(self, items: Iterable[dict], mission_type: int, timeout: float, clear: bool = False) -> int:
        self._check_open()
        items = list(items)
        mav = self._mav
        up = {"items": items, "mission_type": mission_type, "done": threading.Event(), "result": None,
              "requested": threading.Event()}
        self._upload = up
        deadline = time.monotonic() + timeout
        try:
            while time.monotonic() < deadline:
                if clear:
                    self._send("mission_clear_all_send", self.target_system, self.target_component, mission_type)
                else:
                    self._send("mission_count_send", self.target_system, self.target_component, len(items),
                               mission_type)
                # resend the count only if the vehicle has not started asking for items
                if up["done"].wait(min(self.ack_timeout, max(deadline - time.monotonic(), 0.0))):
                    break
                if up["requested"].is_set():
                    up["done"].wait(max(deadline - time.monotonic(), 0.0))
                    break
        finally:
            self._upload = None
        if not up["done"].is_set():
            raise LinkError(self.uri, f"fence upload did not finish within {timeout:.1f} s",
                            "check the link; the vehicle may not support the fence mission type")
        if up["result"] != mav.MAV_MISSION_ACCEPTED:
            raise LinkError(self.uri, f"fence refused: {_name(mav, 'MAV_MISSION_', up['result'])}",
                            "check the fence (convex polygon, a few dozen items at most)")
        logger.info("%s: fence %s (%d items)", self.uri, "cleared" if clear else "uploaded", len(items))
        return len(items)

    def _on_mission_request(self, msg: Any) -> None:
        up = self._upload
        if up is None or msg.mission_type != up["mission_type"]:
            return
        up["requested"].set()
        seq = msg.seq
        if not 0 <= seq < len(up["items"]):
            logger.warning("%s: vehicle asked for fence item %d of %d", self.uri, seq, len(up["items"]))
            return
        it = up["items"][seq]
        self._send("mission_item_int_send", self.target_system, self.target_component, seq,
                   self._mav.MAV_FRAME_GLOBAL_INT, it["command"], 0, 1, it["param1"], 0.0, 0.0, 0.0,
                   int(it["x"]), int(it["y"]), float(it["z"]), up["mission_type"])

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


def _name(mav: Any, prefix: str, value: Any) -> str:
    """``MAV_RESULT_DENIED`` for (``MAV_RESULT_``, 2); the number itself when it has no name."""
    for k, v in vars(mav).items():
        if k.startswith(prefix) and v == value and not k.endswith("_ENUM_END"):
            return k
    return str(value)
