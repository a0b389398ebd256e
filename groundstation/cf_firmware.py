"""Numbers of the Crazyflie firmware that the ground station and the simulator both depend on, defined once.

Each is copied from bitcraze/crazyflie-firmware (the file is named on each); the simulator
(``groundstation.sim``) behaves by them, and the ground station's safety rules (``safety.py``'s coasting
horizon, ``cflib_link``'s emergency-stop watchdog period, the battery's state of charge) are derived from them.
"""
from __future__ import annotations

import math

import numpy as np

WDT_WARNING_S = 0.5
"""COMMANDER_WDT_TIMEOUT_STABILIZE (``src/modules/src/supervisor.c``) [s]: a setpoint older than this puts a
flying drone in the warning-level-out state: x and y control off, roll and pitch level, z as the setpoint had
it (``supervisorOverrideSetpoint``). The drone coasts horizontally on its momentum."""
WDT_SHUTDOWN_S = 2.0
"""COMMANDER_WDT_TIMEOUT_SHUTDOWN (``supervisor.c``) [s]: a setpoint older than this stops the motors and
locks the supervisor (``supervisorStateExceptFreeFall`` -> ``supervisorStateLocked``, reboot required)."""
ESTOP_WATCHDOG_S = 1.0
"""DEFAULT_EMERGENCY_STOP_WATCHDOG_TIMEOUT (``supervisor.c``) [s]: once a first emergency-stop-watchdog
packet has arrived (``crtp_supervisor.c`` CMD_EMERGENCY_STOP_WATCHDOG, or the deprecated
``crtp_localization_service.c`` EMERGENCY_STOP_WATCHDOG), a gap longer than this is an emergency stop:
motors off, locked. It stays armed until a reboot."""
IS_FLYING_HYSTERESIS_S = 2.0
"""IS_FLYING_HYSTERESIS_THRESHOLD (``supervisor.c``) [s]: the supervisor reports "flying" until the motors
have been at idle this long (so a drone that has touched down is "landed" 2 s later)."""
LANDING_TIMEOUT_S = 3.0
"""LANDING_TIMEOUT_MS (``src/platform/interface/platform_defaults.h``) [s]: time in the landed state before
the supervisor resets (disarms, runs its preflight checks again, re-arms automatically)."""
PREDICT_RATE_HZ = 100.0
"""PREDICT_RATE (``src/modules/src/estimator/estimator_kalman.c``) [Hz]: Kalman prediction steps per second."""
PROC_NOISE_ACC_XY = 0.5
"""procNoiseAcc_xy (``kalman_core_params_defaults.h``) [m/s^2]: added to the velocity variance as
``(procNoiseAcc * dt)^2`` per prediction step (``kalman_core.c`` kalmanCoreAddProcessNoise)."""
PROC_NOISE_ACC_Z = 1.0
"""procNoiseAcc_z (``kalman_core_params_defaults.h``, default configuration) [m/s^2]."""
MAX_COVARIANCE = 100.0
"""MAX_COVARIANCE (``kalman_core.c``) [m^2]: the estimator bounds every covariance entry by this."""
LIPO_CHARGE_CURVE_V = (3.00, 3.78, 3.83, 3.87, 3.89, 3.92, 3.96, 4.00, 4.04, 4.10, 4.20)
"""Resting voltage [V] of a 1S LiPo at 0 %, 10 %, ..., 100 % charge: ``LiPoTypicalChargeCurve``
(``src/hal/src/pm_stm32f4.c``, 0-90 %) plus the full-charge voltage 4.2 V. The knee: the last 10 % of the
charge spans 0.78 V, the 80 % above it only 0.32 V."""
BAT_LOW_VOLTAGE = 3.2
"""DEFAULT_BAT_LOW_VOLTAGE (``platform_defaults_cf2.h``) [V]: the firmware's low-battery warning level."""

_SOC_GRID = np.linspace(0.0, 1.0, len(LIPO_CHARGE_CURVE_V))


def lipo_resting_voltage(soc: float) -> float:
    """Resting (open-circuit) voltage [V] of a 1S LiPo at state of charge ``soc`` [0..1] (clipped)."""
    return float(np.interp(min(max(soc, 0.0), 1.0), _SOC_GRID, LIPO_CHARGE_CURVE_V))


def lipo_state_of_charge(voltage: float) -> float:
    """State of charge [0..1] of a 1S LiPo from its voltage [V] by the inverse of the charge curve (a voltage
    under load reads low: compare like with like). Non-finite voltages read as empty."""
    if not math.isfinite(voltage):
        return 0.0
    return float(np.interp(voltage, LIPO_CHARGE_CURVE_V, _SOC_GRID))
