"""The MAVLink side of the ground station that holds no link: URIs, frames, pymavlink plumbing, constants.

Shared by ``MavlinkLink`` and the simulated vehicle (``groundstation.sim.mavlink_vehicle``).

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

Frames. The ground station's world frame is ENU-like: x east, y north, z up, yaw counter-clockwise from x.
MAVLink's local frame is NED: x north, y east, z down, yaw clockwise from north. The link converts every
position, velocity and yaw in both directions (``enu_to_ned`` / ``ned_to_enu``, swap x and y, negate z;
``yaw_ned = pi/2 - yaw_enu``; ``yaw_rate_ned = -yaw_rate_enu``), so callers never see NED.
"""
from __future__ import annotations

import math
from typing import Any

from groundstation.link import LinkError

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


def mav_name(mav: Any, prefix: str, value: Any) -> str:
    """``MAV_RESULT_DENIED`` for (``MAV_RESULT_``, 2); the number itself when it has no name."""
    for k, v in vars(mav).items():
        if k.startswith(prefix) and v == value and not k.endswith("_ENUM_END"):
            return k
    return str(value)
