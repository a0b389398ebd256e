"""The simulated MAVLink vehicle's failsafes and mode transitions, per firmware (a mixin of
``groundstation.sim.mavlink_vehicle.MavlinkVehicle``, whose state it uses; the firmware rules are cited there and
at each rule here): the GCS-loss, offboard-loss and fence failsafes, and what the vehicle does on entering a mode
(LAND, RTL, a hold)."""
from __future__ import annotations

import logging
import math
from typing import Any, Callable

import numpy as np

from groundstation.sim.mavlink_commands import AIRBORNE, VehicleMode

logger = logging.getLogger("groundstation.sim.mavlink_vehicle")

LAND_PAUSE = 4.0
"""A failsafe LAND waits this long before descending [s] (``LAND_WITH_DELAY_MS`` in ``ArduCopter/config.h``)."""


class VehicleModes:
    """Failsafes (``_failsafes``, once per physics step) and mode changes (``_enter_mode``)."""

    params: dict[str, float]
    px4: bool
    mode: VehicleMode
    flight_mode: str
    quad: Any
    home: np.ndarray
    config: Any
    clock: Callable[[], float]
    fence_breaches: int
    failsafe_landings: int
    fence: Any
    fence_ceiling: float
    _target: np.ndarray
    _last_gcs: float
    _stream_t: float
    _setpoint_t: float
    _gcs_failsafe: bool
    _land_pause_until: float
    _landed_at: float | None
    _descent: float | None

    # ---- failsafes ---------------------------------------------------------------------------------

    def _failsafes(self, now: float) -> None:
        p = self.quad.pos[0]
        silent = now - self._last_gcs
        if self.px4:
            if self.flight_mode == "OFFBOARD" and now - self._stream_t > self.params["COM_OF_LOSS_T"] \
                    and self.mode in AIRBORNE:
                action = {3: "RTL", 4: "LAND"}.get(int(self.params["COM_OBL_RC_ACT"]), "LOITER")
                self._failsafe(f"offboard setpoints lost for {now - self._stream_t:.2f} s", action)
            dll = {1: "LOITER", 2: "RTL", 3: "LAND"}.get(int(self.params["NAV_DLL_ACT"]))
            if dll and math.isfinite(self._last_gcs) and silent > self.params["COM_DL_LOSS_T"] \
                    and not self._gcs_failsafe and self.armed:
                self._gcs_failsafe = True
                if self.mode in AIRBORNE:
                    self._failsafe(f"no GCS heartbeat for {silent:.2f} s", dll)
        elif int(self.params["FS_GCS_ENABLE"]) and math.isfinite(self._last_gcs) \
                and silent > self.params["FS_GCS_TIMEOUT"] and not self._gcs_failsafe:
            # ArduCopter events.cpp failsafe_gcs_on_event: once per loss; landed -> disarm; else the action
            self._gcs_failsafe = True
            if self.mode is VehicleMode.IDLE:
                self._disarm("GCS failsafe on the ground")
            elif self.mode in AIRBORNE:
                action = "LAND" if int(self.params["FS_GCS_ENABLE"]) in (4, 5, 7) else "RTL"
                # do_failsafe_action(LAND): set_mode_land_with_pause
                self._failsafe(f"no GCS heartbeat for {silent:.2f} s", action, pause=True)
        if self._fence_on() and self.mode in AIRBORNE and not self.fence.contains(p, self.fence_ceiling):
            self.fence_breaches += 1
            if self.px4:
                action = {2: "LOITER", 3: "RTL", 5: "LAND"}.get(int(self.params["GF_ACTION"]))
            else:
                action = {1: "RTL", 2: "LAND"}.get(int(self.params["FENCE_ACTION"]), "LAND")
            if action is not None:  # ArduCopter fence.cpp: a plain set_mode(LAND), no pause
                self._failsafe(f"fence breached at ({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f})", action)
        if not self.px4 and self.mode is VehicleMode.VELOCITY \
                and now - self._setpoint_t > max(self.params["GUID_TIMEOUT"], 0.1):
            # ModeGuided: a velocity target older than GUID_TIMEOUT is replaced by a stop
            self._target = p.copy()
            self.mode = VehicleMode.HOLD

    def _failsafe(self, why: str, action: str, pause: bool = False) -> None:
        if self.flight_mode == action:
            return
        logger.warning("vehicle %d: %s: %s", self.config.system_id, why, action)
        self.failsafe_landings += action in ("LAND", "RTL")
        self._enter_mode(action, pause=pause and action == "LAND")

    # ---- modes -------------------------------------------------------------------------------------

    def _enter_mode(self, name: str, pause: bool = False) -> None:
        """Switch the autopilot's mode and what the vehicle does in it."""
        if name != self.flight_mode:
            logger.info("vehicle %d: mode %s -> %s", self.config.system_id, self.flight_mode, name)
        self.flight_mode = name
        airborne = self.mode in AIRBORNE or self.mode is VehicleMode.LAND
        if name == "LAND":
            if airborne:
                self._start_land(pause)
            elif self.mode is VehicleMode.IDLE and not self.px4:
                self._disarm("LAND on the ground")
        elif name == "RTL" and airborne:
            z = max(self.quad.pos[0, 2], self._rtl_altitude())
            self._target = np.array([self.home[0], self.home[1], z])
            self.mode = VehicleMode.RTL
        elif name == "TAKEOFF":
            pass  # started by the takeoff command (or by arming while in TAKEOFF)
        elif airborne:  # GUIDED, LOITER, OFFBOARD, POSCTL, BRAKE...: hold where it is until told otherwise
            self._target = self._stopping_point()
            self.mode = VehicleMode.HOLD

    def _rtl_altitude(self) -> float:
        p = self.params
        alt = self.home[2] + (p["RTL_RETURN_ALT"] if self.px4 else p["RTL_ALT"] / 100.0)
        margin = 0.0 if self.px4 else p["FENCE_MARGIN"]
        return min(alt, self.fence_ceiling - margin)

    def _stopping_point(self) -> np.ndarray:
        return self.quad.pos[0] + self.quad.vel[0] / max(self.config.quad.kp_pos, 1e-3)

    def _start_land(self, pause: bool = False) -> None:
        self._target = self.quad.pos[0].copy()
        self._land_pause_until = self.clock() + LAND_PAUSE if pause else -math.inf
        self.mode = VehicleMode.LAND
        self.flight_mode = "LAND"

    def _disarm(self, why: str) -> None:
        logger.info("vehicle %d: disarmed (%s)", self.config.system_id, why)
        self.mode = VehicleMode.DISARMED
        self._landed_at = None
        self._descent = None
