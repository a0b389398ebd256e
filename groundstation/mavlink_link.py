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

Protocol: MAVLink 2, common dialect. The link sends a GCS ``HEARTBEAT`` every ``heartbeat_period`` (0.25 s)
from its own thread; vehicles land by themselves when these stop (``close()`` therefore ends in a failsafe
landing after the vehicle's timeout, 1 s for the simulated vehicle). On opening it waits for the vehicle's
heartbeat, asks for ``LOCAL_POSITION_NED``, ``SYS_STATUS`` and ``EXTENDED_SYS_STATE`` streams with
``MAV_CMD_SET_MESSAGE_INTERVAL`` and waits for the first full telemetry sample.

Frames. The ground station's world frame is ENU-like: x east, y north, z up, yaw counter-clockwise from x.
MAVLink's local frame is NED: x north, y east, z down, yaw clockwise from north. The link converts every
position, velocity and yaw in both directions (``enu_to_ned`` / ``ned_to_enu``, swap x and y, negate z;
``yaw_ned = pi/2 - yaw_enu``; ``yaw_rate_ned = -yaw_rate_enu``), so callers never see NED.

Commands. ``send_velocity`` / ``send_position`` stream ``SET_POSITION_TARGET_LOCAL_NED`` (type masks
``VELOCITY_MASK`` / ``POSITION_MASK``, frame ``MAV_FRAME_LOCAL_NED``). ``takeoff`` arms
(``MAV_CMD_COMPONENT_ARM_DISARM``) when needed, sets the climb speed to ``height / duration``
(``MAV_CMD_DO_CHANGE_SPEED`` speed type 2) and sends ``MAV_CMD_NAV_TAKEOFF`` with param7 = height [m above
the local origin]. ``land`` sets the descent speed (speed type 3) and sends ``MAV_CMD_NAV_LAND`` with
param7 = landing height; the vehicle disarms on touchdown. ``emergency_stop`` sends
``MAV_CMD_DO_FLIGHTTERMINATION``. Every command waits for its ``COMMAND_ACK`` and raises ``LinkError``
when it is refused or unanswered.

Fence upload (``upload_fence``): the MAVLink mission protocol with ``mission_type = MAV_MISSION_TYPE_FENCE``
(``MISSION_COUNT`` -> ``MISSION_REQUEST_INT`` / ``MISSION_ITEM_INT`` per item -> ``MISSION_ACK``), items in
``MAV_FRAME_LOCAL_NED`` with x, y = north, east [m] x 1e4: one ``MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION``
per polygon corner (param1 = corner count) and one ``MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION`` per keep-out
circle (param1 = radius [m]). The fence's ceiling travels as z = -z_max [m, NED] of the inclusion corners, a
local convention that our simulated vehicle reads and that PX4 and ArduPilot ignore (set their altitude
limits by parameter). The vehicle gets the fence itself, without the margin: it is the backstop behind the
ground station's geofence, which keeps setpoints a margin inside.
"""
from __future__ import annotations

import collections
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterable

from groundstation.link import FlightState, Link, LinkError, LinkStats, Telemetry

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
LOCAL_XY_SCALE = 1e4
"""``MISSION_ITEM_INT`` x, y in local frames: metres x 1e4."""


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


def fence_items(fence: "FenceConfig") -> list[dict[str, float | int]]:
    """The fence as ``MISSION_ITEM_INT`` fields (see the module docstring), in upload order."""
    mav = mavlink_module()
    items: list[dict[str, float | int]] = []
    poly = fence.polygon
    for x, y in poly:
        n, e, _ = enu_to_ned(float(x), float(y), 0.0)
        items.append({"command": mav.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, "param1": float(len(poly)),
                      "param2": 0.0, "x": round(n * LOCAL_XY_SCALE), "y": round(e * LOCAL_XY_SCALE),
                      "z": -float(fence.z_max)})
    for k in fence.keep_out:
        n, e, _ = enu_to_ned(k.x, k.y, 0.0)
        items.append({"command": mav.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION, "param1": float(k.radius),
                      "param2": 0.0, "x": round(n * LOCAL_XY_SCALE), "y": round(e * LOCAL_XY_SCALE), "z": 0.0})
    return items


# --------------------------------------------------------------------------------------------------
# the link


@dataclass
class _Pending:
    event: threading.Event
    result: Any = None


class MavlinkLink(Link):
    """One MAVLink vehicle. Opening blocks until its heartbeat and a full telemetry sample arrived.

    >>> with MavlinkLink("mavlink:udpin:127.0.0.1:14550") as link:
    ...     link.takeoff(1.0, 2.0)
    """

    def __init__(self, uri: str, *, connect_timeout: float = 10.0, heartbeat_period: float = 0.25,
                 telemetry_rate: float = 50.0, period_ms: int | None = None, link_loss_timeout: float = 0.25,
                 ack_timeout: float = 1.0, retries: int = 3, source_system: int = 255,
                 source_component: int = 190) -> None:
        """``period_ms``, when given, sets the telemetry period like ``CflibLink(period_ms=...)`` and overrides
        ``telemetry_rate`` [Hz]."""
        super().__init__(uri)
        self.connection = parse_uri(uri)
        if period_ms is not None:
            if not 1 <= period_ms <= 10_000:
                raise LinkError(uri, f"period_ms must be in 1..10000, got {period_ms}",
                                "pass the telemetry period in milliseconds, e.g. period_ms=20")
            telemetry_rate = 1000.0 / period_ms
        if not telemetry_rate > 0:
            raise LinkError(uri, f"telemetry_rate must be positive, got {telemetry_rate}",
                            "pass the telemetry rate in Hz, e.g. telemetry_rate=50")
        self.heartbeat_period = heartbeat_period
        self.telemetry_rate = telemetry_rate
        self.link_loss_timeout = link_loss_timeout
        self.ack_timeout = ack_timeout
        self.retries = retries
        self.target_system: int | None = None
        self.target_component: int = 1
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
        self._upload: dict[str, Any] | None = None
        self._armed = False
        self._terminated = False
        self._landed_state = self._mav.MAV_LANDED_STATE_UNDEFINED
        self._battery_v = math.nan
        self._last_heartbeat = -math.inf
        self._got_heartbeat = threading.Event()
        self._arrivals: collections.deque[float] = collections.deque(maxlen=max(2, int(2 * telemetry_rate)))
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name=f"mavlink-link {self.connection}", daemon=True)
        self._thread.start()
        try:
            if not self._got_heartbeat.wait(connect_timeout):
                raise LinkError(uri, f"no vehicle heartbeat within {connect_timeout:.1f} s",
                                "start the vehicle or simulator and check that it sends to this address "
                                "(udpin listens, udpout sends first)")
            self._request_streams()
            self.wait_telemetry(connect_timeout, lambda s: not math.isnan(s.battery))
        except LinkError:
            self.close()
            raise

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
            if msg.type in (mav.MAV_TYPE_GCS, mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_TYPE_GIMBAL):
                return
            if self.target_system is None:
                self.target_system, self.target_component = src, msg.get_srcComponent()
                logger.info("%s: vehicle %d/%d (autopilot %d, type %d)", self.uri, src, self.target_component,
                            msg.autopilot, msg.type)
            if src != self.target_system:
                return
            self._armed = bool(msg.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
            self._terminated = msg.system_status in (mav.MAV_STATE_FLIGHT_TERMINATION, mav.MAV_STATE_EMERGENCY)
            self._last_heartbeat = time.monotonic()
            self._got_heartbeat.set()
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
        elif kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            self._on_mission_request(msg)
        elif kind == "MISSION_ACK":
            up = self._upload
            if up is not None and msg.mission_type == up["mission_type"]:
                up["result"] = msg.type
                up["done"].set()

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
    def flight_state(self) -> FlightState:
        """From the heartbeat's armed flag and system status and ``EXTENDED_SYS_STATE.landed_state``."""
        mav = self._mav
        if self._terminated:
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

    def command(self, command: int, *params: float, timeout: float | None = None) -> int:
        """Send ``COMMAND_LONG`` (up to 7 params) and wait for its ``COMMAND_ACK``; returns the ``MAV_RESULT``.
        Retried ``retries`` times (with the confirmation counter) when unanswered; ``LinkError`` then."""
        self._check_open()
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        pending = _Pending(threading.Event())
        self._acks[command] = pending
        try:
            for attempt in range(self.retries + 1):
                self._send("command_long_send", self.target_system, self.target_component, command, attempt, *p)
                if pending.event.wait(timeout or self.ack_timeout):
                    return int(pending.result)
        finally:
            self._acks.pop(command, None)
        raise LinkError(self.uri, f"command {command} unanswered after {self.retries + 1} tries",
                        "check the link; the vehicle may not support this command")

    def _command_ok(self, command: int, what: str, *params: float) -> None:
        result = self.command(command, *params)
        if result != self._mav.MAV_RESULT_ACCEPTED:
            names = {v: k for k, v in vars(self._mav).items() if k.startswith("MAV_RESULT_")}
            raise LinkError(self.uri, f"{what} refused: {names.get(result, result)}",
                            "check the vehicle's state (armed, on the ground, not locked by a failsafe)")

    def _request_streams(self) -> None:
        mav = self._mav
        period_us = 1e6 / self.telemetry_rate
        for msg_id, interval in ((mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, period_us),
                                 (mav.MAVLINK_MSG_ID_SYS_STATUS, 2e5),
                                 (mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2e5)):
            result = self.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval)
            if result != mav.MAV_RESULT_ACCEPTED:
                logger.warning("%s: vehicle refused the stream rate of message %d (result %d); using its default",
                               self.uri, msg_id, result)

    def send_velocity(self, vx: float, vy: float, vz: float, yaw_rate: float = 0.0) -> None:
        self._check_open()
        n, e, d = enu_to_ned(vx, vy, vz)
        self._send("set_position_target_local_ned_send", self._time_boot_ms(), self.target_system,
                   self.target_component, self._mav.MAV_FRAME_LOCAL_NED, VELOCITY_MASK, 0.0, 0.0, 0.0, n, e, d,
                   0.0, 0.0, 0.0, 0.0, -float(yaw_rate))

    def send_position(self, x: float, y: float, z: float, yaw: float = 0.0) -> None:
        self._check_open()
        n, e, d = enu_to_ned(x, y, z)
        self._send("set_position_target_local_ned_send", self._time_boot_ms(), self.target_system,
                   self.target_component, self._mav.MAV_FRAME_LOCAL_NED, POSITION_MASK, n, e, d, 0.0, 0.0, 0.0,
                   0.0, 0.0, 0.0, yaw_enu_to_ned(yaw), 0.0)

    def arm(self) -> None:
        self._command_ok(self._mav.MAV_CMD_COMPONENT_ARM_DISARM, "arming", 1.0)

    def disarm(self, force: bool = False) -> None:
        """Disarm; vehicles refuse in the air unless ``force`` (then the motors stop and it falls)."""
        self._command_ok(self._mav.MAV_CMD_COMPONENT_ARM_DISARM, "disarming", 0.0,
                         FORCE_DISARM_MAGIC if force else 0.0)

    def takeoff(self, height: float, duration: float) -> None:
        mav = self._mav
        self._check_open()
        if not self._armed:
            self.arm()
        latest = self.telemetry()
        z0 = latest.position[2] if latest is not None else 0.0
        if duration > 0 and height > z0:
            self._command_ok(mav.MAV_CMD_DO_CHANGE_SPEED, "climb speed", 2.0, (height - z0) / duration, -1.0)
        self._command_ok(mav.MAV_CMD_NAV_TAKEOFF, "takeoff", 0, 0, 0, math.nan, math.nan, math.nan, height)

    def land(self, duration: float, height: float = 0.0) -> None:
        mav = self._mav
        self._check_open()
        latest = self.telemetry()
        if latest is not None and duration > 0 and latest.position[2] > height:
            self._command_ok(mav.MAV_CMD_DO_CHANGE_SPEED, "descent speed", 3.0,
                             (latest.position[2] - height) / duration, -1.0)
        self._command_ok(mav.MAV_CMD_NAV_LAND, "landing", 0, 0, 0, math.nan, math.nan, math.nan, height)

    def emergency_stop(self) -> None:
        """``MAV_CMD_DO_FLIGHTTERMINATION``, sent three times without waiting (a lost packet must not delay
        it). The vehicle cuts its motors and stays locked until rebooted."""
        self._check_open()
        for attempt in range(3):
            self._send("command_long_send", self.target_system, self.target_component,
                       self._mav.MAV_CMD_DO_FLIGHTTERMINATION, attempt, 1.0, 0, 0, 0, 0, 0, 0)

    # ---- fence -------------------------------------------------------------------------------------

    def upload_fence(self, fence: "FenceConfig", timeout: float = 5.0) -> int:
        """Upload ``fence`` with the mission protocol (see the module docstring); returns the item count.
        ``LinkError`` when the vehicle refuses it or the transfer does not finish within ``timeout`` [s]."""
        return self._upload_items(fence_items(fence), self._mav.MAV_MISSION_TYPE_FENCE, timeout)

    def clear_fence(self, timeout: float = 2.0) -> None:
        """Remove the vehicle's fence (``MISSION_CLEAR_ALL`` with the fence mission type)."""
        self._upload_items([], self._mav.MAV_MISSION_TYPE_FENCE, timeout, clear=True)

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
            names = {v: k for k, v in vars(mav).items() if k.startswith("MAV_MISSION_") and isinstance(v, int)}
            raise LinkError(self.uri, f"fence refused: {names.get(up['result'], up['result'])}",
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
                   self._mav.MAV_FRAME_LOCAL_NED, it["command"], 0, 1, it["param1"], it["param2"], 0.0, 0.0,
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
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)
        with self._send_lock:
            self._conn.close()
