"""What a ``MavlinkLink`` asks of its vehicle: commands with their acknowledgements, parameters, modes,
takeoff, landing, the emergency stop and the fence upload (a part of ``MavlinkLink``; the receive thread in
``mavlink_link`` answers the waits here).

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

import concurrent.futures
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterable

from groundstation.link import Link, LinkError
from groundstation.mavlink_autopilot import (COPTER_MODES, NOT_ARMABLE, PX4_MODES, Autopilot, GlobalOrigin,
                                             fence_items, fence_params, set_mode_params)
from groundstation.mavlink_wire import FORCE_DISARM_MAGIC, mav_name
from groundstation.mavlink_worker import CommandWorker

if TYPE_CHECKING:
    from groundstation.safety import FenceConfig

logger = logging.getLogger("groundstation.mavlink_link")


@dataclass
class _Pending:
    event: threading.Event
    result: Any = None


class MavlinkOperations(Link):
    """The command side of ``MavlinkLink`` (which sets every attribute used here in its ``__init__``)."""

    _mav: Any
    _worker: CommandWorker
    _acks: dict[int, _Pending]
    _params: dict[str, _Pending]
    _upload: dict[str, Any] | None
    autopilot: Autopilot | None
    origin: GlobalOrigin | None
    target_system: int | None
    target_component: int
    retries: int
    ack_timeout: float
    mode: str
    """The vehicle's flight mode (``MavlinkLink.mode``, from its heartbeats)."""
    _armed: bool
    _terminated: bool
    _estopped: bool
    _want_offboard: bool

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
        raise LinkError(self.uri, f"command {mav_name(self._mav, 'MAV_CMD_', command)} unanswered after "
                                  f"{self.retries + 1} tries of {timeout or self.ack_timeout:.2f} s",
                        "check the link; the vehicle may not support this command")

    def _command_ok(self, command: int, what: str, *params: float) -> None:
        result = self.command(command, *params)
        if result != self._mav.MAV_RESULT_ACCEPTED:
            raise LinkError(self.uri, f"{what} refused: {mav_name(self._mav, 'MAV_RESULT_', result)} "
                                      f"(mode {self.mode})",
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

    # ---- takeoff, landing, stop (queued on the worker) ---------------------------------------------

    def _check_flyable(self) -> None:
        self._check_open()
        if self._terminated or self._estopped:
            raise LinkError(self.uri, "the vehicle is locked by a flight termination (emergency stop)",
                            "reboot it: link.command(MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)")

    def takeoff(self, height: float, duration: float) -> concurrent.futures.Future:
        """Queue the takeoff to ``height`` [m, world z] and return its future at once: ArduPilot GUIDED, arm,
        climb speed, ``NAV_TAKEOFF`` (param7 above home); PX4 (out of a mode it will not arm in, to HOLD,) arm,
        ``NAV_TAKEOFF`` (param7 AMSL from the EKF origin), then OFFBOARD once setpoints stream. ``LinkError`` now
        only for a closed or locked link; a refused step fails the future (and is logged, and kept in
        ``command_errors``).

        Once the vehicle has accepted a takeoff, asking again (the flight supervisor re-sends a takeoff whose
        vehicle still reports itself on the ground, for a command that a radio link lost) returns a finished
        future and sends nothing, until the flight ends (a landing, an emergency stop, or a disarm). Both
        firmwares refuse a second ``NAV_TAKEOFF`` while climbing, and their landed state lags the ack by a
        telemetry period or more."""
        self._check_flyable()
        if self._takeoff_under_way:
            logger.debug("%s: takeoff already accepted and under way: not sent again", self.uri)
            done: concurrent.futures.Future = concurrent.futures.Future()
            done.set_result(None)
            return done
        self._worker.preempt(("land",))
        return self._worker.submit("takeoff", lambda: self._takeoff(height, duration))

    def _takeoff(self, height: float, duration: float) -> None:
        mav = self._mav
        if self.autopilot is Autopilot.PX4:
            if self.origin is None:
                raise LinkError(self.uri, "PX4 takeoff needs the EKF origin (GPS_GLOBAL_ORIGIN)",
                                "set the vehicle's EKF origin before flying")
            if not self._armed:
                if self.mode in NOT_ARMABLE[Autopilot.PX4]:  # landed itself: PX4 stays in LAND, and arms in HOLD
                    self.set_mode("LOITER")
                self._command_ok(mav.MAV_CMD_COMPONENT_ARM_DISARM, "arming", 1.0)
            self._want_offboard = True
            self._command_ok(mav.MAV_CMD_NAV_TAKEOFF, "takeoff", 0, 0, 0, math.nan, math.nan, math.nan,
                             self.origin.alt + height)
            self._takeoff_under_way = True
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
                            mav_name(mav, "MAV_RESULT_", result))
        self._command_ok(mav.MAV_CMD_NAV_TAKEOFF, "takeoff", 0, 0, 0, math.nan, math.nan, math.nan, height)
        self._takeoff_under_way = True

    def land(self, duration: float, height: float = 0.0) -> concurrent.futures.Future:
        """Queue ``MAV_CMD_NAV_LAND`` (both firmwares switch to their LAND mode, descend at their landing speed
        and disarm on the ground; ``duration`` and ``height`` are theirs to choose) and return its future.
        A queued or hanging takeoff is abandoned first. Repeated calls while one is in flight share it."""
        self._check_open()
        self._want_offboard = False
        self._takeoff_under_way = False
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
        self._takeoff_under_way = False
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
            raise LinkError(self.uri, f"fence refused: {mav_name(mav, 'MAV_MISSION_', up['result'])}",
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
