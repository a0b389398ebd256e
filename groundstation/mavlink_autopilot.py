"""What differs between the autopilots a ``MavlinkLink`` flies: flight modes, global frame, fence upload.

One definition for both sides (the link and ``groundstation.sim.mavlink_vehicle``); pure functions only.

Flight modes. ``HEARTBEAT.custom_mode`` carries the mode:

* ArduCopter: the mode number itself (``ArduCopter/mode.h``, ``enum class Mode::Number``: STABILIZE 0,
  ALT_HOLD 2, AUTO 3, GUIDED 4, LOITER 5, RTL 6, LAND 9, BRAKE 17; ``GCS_Copter::custom_mode()`` in
  ``ArduCopter/GCS_MAVLink_Copter.cpp``). Set with ``MAV_CMD_DO_SET_MODE`` (param1 = base mode with
  ``MAV_MODE_FLAG_CUSTOM_MODE_ENABLED``, param2 = mode number) or the ``SET_MODE`` message.
* PX4: ``union px4_custom_mode`` (``src/modules/commander/px4_custom_mode.h``): ``uint16 reserved; uint8
  main_mode; uint8 sub_mode``, i.e. ``custom_mode = main << 16 | sub << 24``; main modes POSCTL 3, AUTO 4,
  OFFBOARD 6; AUTO sub modes TAKEOFF 2, LOITER 3 (Hold), RTL 5, LAND 6. ``MAV_CMD_DO_SET_MODE`` takes
  param1 = base mode, param2 = main mode, param3 = sub mode.

The names are pymavlink's (``mavutil.mode_mapping_acm``, ``mavutil.px4_map``, ``mavutil.interpret_px4_mode``),
so ``conn.set_mode("GUIDED")`` in an ordinary pymavlink script and this code mean the same numbers.

Global frame. Both autopilots take fences (and PX4 its takeoff altitude) in latitude / longitude / AMSL, and
report ``LOCAL_POSITION_NED`` relative to the EKF origin, which ``GPS_GLOBAL_ORIGIN`` gives. ``local_to_global``
and ``global_to_local`` convert with ArduPilot's flat-earth scaling (``libraries/AP_Common/Location.cpp``,
``LOCATION_SCALING_FACTOR`` = 0.011131884502145034 m per 1e-7 degree, longitude scaled by cos(latitude)), exact
to millimetres over an arena.

Fences (``fence_plan``): both take the inclusion polygon and exclusion circles as mission items with
``mission_type = MAV_MISSION_TYPE_FENCE`` in ``MAV_FRAME_GLOBAL_INT`` (x, y = lat, lon x 1e7;
``MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION`` with param1 = vertex count, ``MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION``
with param1 = radius [m]). The ceiling and what the vehicle does on a breach are parameters:
ArduCopter ``FENCE_ENABLE`` 1, ``FENCE_TYPE`` = 1 (max altitude) | 4 (polygon), ``FENCE_ALT_MAX`` [m above
home], ``FENCE_ACTION`` 2 (always land; ``libraries/AC_Fence/AC_Fence.cpp``); PX4 ``GF_ACTION`` 5 (land),
``GF_MAX_VER_DIST`` [m above home] (``src/modules/navigator/geofence_params.c``).
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from groundstation.safety import FenceConfig

LOCATION_SCALING_FACTOR = 0.011131884502145034
"""[m] per 1e-7 degree of latitude (ArduPilot ``AP_Common/Location.cpp``)."""

COPTER_MODES = {"STABILIZE": 0, "ACRO": 1, "ALT_HOLD": 2, "AUTO": 3, "GUIDED": 4, "LOITER": 5, "RTL": 6,
                "CIRCLE": 7, "LAND": 9, "POSHOLD": 16, "BRAKE": 17}
"""ArduCopter ``Mode::Number`` (``ArduCopter/mode.h``), the subset a multicopter GCS uses."""

PX4_MAIN_POSCTL, PX4_MAIN_AUTO, PX4_MAIN_OFFBOARD = 3, 4, 6
PX4_SUB_TAKEOFF, PX4_SUB_LOITER, PX4_SUB_RTL, PX4_SUB_LAND = 2, 3, 5, 6
PX4_MODES = {"POSCTL": (PX4_MAIN_POSCTL, 0), "OFFBOARD": (PX4_MAIN_OFFBOARD, 0),
             "TAKEOFF": (PX4_MAIN_AUTO, PX4_SUB_TAKEOFF), "LOITER": (PX4_MAIN_AUTO, PX4_SUB_LOITER),
             "RTL": (PX4_MAIN_AUTO, PX4_SUB_RTL), "LAND": (PX4_MAIN_AUTO, PX4_SUB_LAND)}
"""PX4 (main, sub) modes by pymavlink's names (``px4_custom_mode.h``)."""

LANDING_MODES = ("LAND", "RTL")
"""Modes in which the vehicle brings itself down: the link never switches a vehicle out of them."""


class Autopilot(str, enum.Enum):
    ARDUPILOT = "ardupilot"
    PX4 = "px4"

    @classmethod
    def from_heartbeat(cls, autopilot: int) -> "Autopilot | None":
        from groundstation.mavlink_wire import mavlink_module
        mav = mavlink_module()
        return {mav.MAV_AUTOPILOT_ARDUPILOTMEGA: cls.ARDUPILOT, mav.MAV_AUTOPILOT_PX4: cls.PX4}.get(autopilot)


NOT_ARMABLE = {Autopilot.ARDUPILOT: ("LAND", "RTL", "AUTO"), Autopilot.PX4: ("LAND", "RTL")}
"""Modes in which each firmware refuses to arm (ArduCopter's ``allows_arming`` false; PX4 commander's mode
requirements, ``mode_req_prevent_arming``). A vehicle that landed itself stays in its landing mode: the link's
takeoff switches a disarmed one out of it first, and the simulated vehicle refuses to arm in it."""


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """``union px4_custom_mode`` as the uint32 ``HEARTBEAT.custom_mode``."""
    return (main & 0xFF) << 16 | (sub & 0xFF) << 24


def px4_split(custom_mode: int) -> tuple[int, int]:
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def mode_name(autopilot: Autopilot, custom_mode: int) -> str:
    """The mode's name (pymavlink's spelling); ``"UNKNOWN(n)"`` for others."""
    if autopilot is Autopilot.PX4:
        main, sub = px4_split(custom_mode)
        for name, (m, s) in PX4_MODES.items():
            if m == main and (s == sub or m != PX4_MAIN_AUTO):
                return name
    else:
        for name, number in COPTER_MODES.items():
            if number == custom_mode:
                return name
    return f"UNKNOWN({custom_mode})"


def set_mode_params(autopilot: Autopilot, name: str) -> tuple[float, float, float]:
    """param1..3 of ``MAV_CMD_DO_SET_MODE`` for the mode ``name``; ``KeyError`` for an unknown name."""
    custom_mode_enabled = 1.0  # MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if autopilot is Autopilot.PX4:
        main, sub = PX4_MODES[name]
        return custom_mode_enabled, float(main), float(sub)
    return custom_mode_enabled, float(COPTER_MODES[name]), 0.0


def mode_from_set_mode(autopilot: Autopilot, base_mode: float, p2: float, p3: float) -> str | None:
    """The mode a ``DO_SET_MODE`` (or ``SET_MODE``) asks for, or None when it is not one of ours."""
    if not int(base_mode) & 1:  # no custom mode: neither autopilot changes mode from base flags alone
        return None
    if autopilot is Autopilot.PX4:
        name = mode_name(autopilot, px4_custom_mode(int(p2), int(p3)))
    else:
        name = mode_name(autopilot, int(p2))
    return None if name.startswith("UNKNOWN") else name


@dataclass(frozen=True)
class GlobalOrigin:
    """The EKF origin (``GPS_GLOBAL_ORIGIN``): where local (0, 0, 0) is."""

    lat: float
    """[deg]"""
    lon: float
    """[deg]"""
    alt: float
    """[m, AMSL]"""


def local_to_global(origin: GlobalOrigin, x: float, y: float) -> tuple[int, int]:
    """World (x east, y north) [m] -> (lat, lon) x 1e7 as ``MISSION_ITEM_INT`` carries them."""
    lat_e7 = origin.lat * 1e7 + y / LOCATION_SCALING_FACTOR
    lon_e7 = origin.lon * 1e7 + x / (LOCATION_SCALING_FACTOR * _lon_scale(origin))
    return round(lat_e7), round(lon_e7)


def global_to_local(origin: GlobalOrigin, lat_e7: int, lon_e7: int) -> tuple[float, float]:
    """(lat, lon) x 1e7 -> world (x east, y north) [m]."""
    y = (lat_e7 - origin.lat * 1e7) * LOCATION_SCALING_FACTOR
    x = (lon_e7 - origin.lon * 1e7) * LOCATION_SCALING_FACTOR * _lon_scale(origin)
    return x, y


def _lon_scale(origin: GlobalOrigin) -> float:
    return max(math.cos(math.radians(origin.lat)), 0.01)


def fence_items(fence: "FenceConfig", origin: GlobalOrigin) -> list[dict[str, Any]]:
    """The fence's polygon and keep-out circles as ``MISSION_ITEM_INT`` fields (global frame), in order."""
    from groundstation.mavlink_wire import mavlink_module
    mav = mavlink_module()
    items: list[dict[str, Any]] = []
    poly = fence.polygon
    for x, y in poly:
        lat, lon = local_to_global(origin, float(x), float(y))
        items.append({"command": mav.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, "param1": float(len(poly)),
                      "x": lat, "y": lon, "z": 0.0})
    for k in fence.keep_out:
        lat, lon = local_to_global(origin, k.x, k.y)
        items.append({"command": mav.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION, "param1": float(k.radius),
                      "x": lat, "y": lon, "z": 0.0})
    return items


def fence_params(autopilot: Autopilot, fence: "FenceConfig") -> list[tuple[str, float]]:
    """Parameters that enable the fence, set its ceiling [m above home] and make a breach land."""
    if autopilot is Autopilot.PX4:
        return [("GF_ACTION", 5.0), ("GF_MAX_VER_DIST", float(fence.z_max))]
    return [("FENCE_TYPE", 5.0), ("FENCE_ALT_MAX", float(fence.z_max)), ("FENCE_ACTION", 2.0),
            ("FENCE_ENABLE", 1.0)]


def failsafe_params(autopilot: Autopilot, gcs_timeout: float) -> list[tuple[str, float]]:
    """Parameters that make the vehicle land by itself when the ground station goes silent.

    ArduCopter: ``FS_GCS_ENABLE`` 5 (land; ``ArduCopter/events.cpp`` ``failsafe_gcs_on_event``), ``FS_GCS_TIMEOUT``.
    PX4: ``NAV_DLL_ACT`` 3 (land), ``COM_DL_LOSS_T``; and ``COM_OBL_RC_ACT`` 4 (land) for the offboard stream's
    loss after ``COM_OF_LOSS_T`` (``src/modules/commander/commander_params.c``). Both defaults are off / hold."""
    if autopilot is Autopilot.PX4:
        return [("NAV_DLL_ACT", 3.0), ("COM_DL_LOSS_T", float(gcs_timeout)), ("COM_OBL_RC_ACT", 4.0)]
    return [("FS_GCS_ENABLE", 5.0), ("FS_GCS_TIMEOUT", float(gcs_timeout))]
