"""The simulated MAVLink vehicle's side of the fence upload (mission protocol, ``MAV_MISSION_TYPE_FENCE``).

Items come in the global frame, as ArduPilot (``libraries/AP_Mission/MissionItemProtocol_Fence.cpp``) and PX4
(``src/modules/mavlink/mavlink_mission.cpp``) take them; local frames are refused with
``MAV_MISSION_UNSUPPORTED_FRAME``. Positions are turned back into the world frame around the vehicle's EKF
origin (``groundstation.mavlink_autopilot.global_to_local``). The ceiling is not in the items: each autopilot
takes it as a parameter (``FENCE_ALT_MAX`` / ``GF_MAX_VER_DIST``), so ``VehicleFence.z_max`` is set from there.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from groundstation.mavlink_autopilot import GlobalOrigin, global_to_local

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class VehicleFence:
    """The fence as uploaded (world frame)."""

    polygon: np.ndarray
    """[n, 2] inclusion corners [m]."""
    circles: tuple[tuple[float, float, float], ...]
    """Exclusion circles (x, y, radius) [m]."""

    def contains(self, p: np.ndarray, z_max: float = math.inf) -> bool:
        if p[2] > z_max:
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


class FenceReceiver:
    """Runs the vehicle's half of the mission protocol for fences; ``fence`` is the accepted one."""

    def __init__(self, mav: Any, send: Callable[[], Any], origin: GlobalOrigin, system_id: int,
                 clock: Callable[[], float]) -> None:
        self._mav, self._send, self.origin, self.system_id, self.clock = mav, send, origin, system_id, clock
        self.fence: VehicleFence | None = None
        self._rx: dict[str, Any] | None = None

    def handle(self, kind: str, msg: Any) -> None:
        mav, m = self._mav, self._send()
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        if msg.mission_type != mav.MAV_MISSION_TYPE_FENCE:
            m.mission_ack_send(src, comp, mav.MAV_MISSION_UNSUPPORTED, msg.mission_type)
            return
        if kind == "MISSION_CLEAR_ALL":
            self.fence, self._rx = None, None
            logger.info("vehicle %d: fence cleared", self.system_id)
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
            m.mission_ack_send(src, comp, self._accept(rx["items"]), msg.mission_type)

    def retry(self, now: float, after: float = 0.5, tries: int = 5) -> None:
        """Ask again for an item that did not come; give up (OPERATION_CANCELLED) after ``tries``."""
        rx, mav = self._rx, self._mav
        if rx is None or now - rx["t"] < after:
            return
        if rx["tries"] >= tries:
            logger.warning("vehicle %d: fence upload stalled at item %d of %d: cancelled", self.system_id,
                           len(rx["items"]), rx["count"])
            self._rx = None
            self._send().mission_ack_send(rx["src"], rx["comp"], mav.MAV_MISSION_OPERATION_CANCELLED,
                                          mav.MAV_MISSION_TYPE_FENCE)
            return
        rx["t"], rx["tries"] = now, rx["tries"] + 1
        self._send().mission_request_int_send(rx["src"], rx["comp"], len(rx["items"]), mav.MAV_MISSION_TYPE_FENCE)

    def _accept(self, items: list[Any]) -> int:
        mav = self._mav
        global_frames = (mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_GLOBAL_INT, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                         mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
        poly: list[tuple[float, float]] = []
        circles: list[tuple[float, float, float]] = []
        for it in items:
            if it.frame not in global_frames:
                return mav.MAV_MISSION_UNSUPPORTED_FRAME
            x, y = global_to_local(self.origin, it.x, it.y)
            if it.command == mav.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION:
                poly.append((x, y))
            elif it.command == mav.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION:
                if not it.param1 > 0:
                    return mav.MAV_MISSION_INVALID_PARAM1
                circles.append((x, y, float(it.param1)))
            else:
                return mav.MAV_MISSION_UNSUPPORTED
        counts = {int(it.param1) for it in items if it.command == mav.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION}
        if poly and (len(poly) < 3 or counts != {len(poly)}):
            return mav.MAV_MISSION_INVALID_PARAM1
        self.fence = VehicleFence(np.array(poly, dtype=float).reshape(-1, 2), tuple(circles))
        logger.info("vehicle %d: fence with %d corners, %d exclusion circles", self.system_id, len(poly),
                    len(circles))
        return mav.MAV_MISSION_ACCEPTED
