"""Physics of the simulated Crazyflies: a batch of position-controlled quadrotors, their position estimates
and their batteries.

Pure numpy, batch-first (``[n_drones, 3]``), no sockets and no clocks: the caller passes ``dt``. The
firmware logic in ``firmware.py`` turns setpoints into a desired velocity per drone; this module turns
desired velocities into motion (first-order response, acceleration and speed limits, coasting against drag
while the firmware has horizontal control off, gravity when the motors are off, ground contact), models the
Loco Positioning estimate (correlated noise, outliers, dropouts) with the Kalman filter's position variance,
and drains the batteries along a LiPo discharge curve.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from groundstation.cf_firmware import (MAX_COVARIANCE, PREDICT_RATE_HZ, PROC_NOISE_ACC_XY, PROC_NOISE_ACC_Z,
                                       lipo_resting_voltage)

GRAVITY = 9.81
"""[m/s^2]"""


@dataclass(frozen=True)
class QuadParams:
    """Flight model of one Crazyflie 2.x with its onboard position controller closed."""

    tau: float = 0.2
    """Time constant of the velocity response to a desired velocity [s]."""
    max_accel: float = 5.0
    """Largest acceleration the controller commands, norm [m/s^2]."""
    max_speed_xy: float = 2.0
    """Horizontal speed limit [m/s]."""
    max_speed_z: float = 1.0
    """Vertical speed limit [m/s]."""
    kp_pos: float = 2.0
    """Position-error gain of the position controller [1/s]: desired velocity = kp_pos * error."""
    drag_xy: float = 0.3
    """Horizontal linear drag per unit mass with the rotors at hover [1/s]: what slows a levelled drone
    whose horizontal control is off. Estimate from the Crazyflie 2.0 identification (Foerster 2015): drag
    about 1e-6 kg/rad times the sum of the rotor speeds (4 x 2000 rad/s at hover) over 0.027 kg."""
    ground_z: float = 0.0
    """Floor height [m]."""
    lps_sigma_xy: float = 0.03
    """Standard deviation of the horizontal position-estimate error, like the Loco Positioning System [m];
    also the steady state of the reported ``kalman.varPX``/``varPY`` (its square)."""
    lps_sigma_z: float = 0.04
    """Standard deviation of the vertical position-estimate error [m]."""
    lps_corr_time: float = 0.3
    """Correlation time of the position-estimate error (Gauss-Markov) [s]; outliers and the drift left by a
    dropout also fade with it once measurements are back."""
    lps_outlier_rate: float = 0.1
    """Outliers (a multipath or non-line-of-sight UWB range that passes the estimator's outlier filter) per
    second and drone [1/s]: each moves the estimate by a random offset that then fades."""
    lps_outlier_m: float = 0.05
    """Mean size of an outlier's offset [m] (exponentially distributed)."""
    lps_dropout_rate: float = 0.02
    """Positioning dropouts (no measurement reaches the estimator) per second and drone [1/s]. Meanwhile the
    estimate dead-reckons and its variance grows as the Kalman filter's prediction makes it."""
    lps_dropout_mean_s: float = 0.2
    """Mean duration of a random dropout [s] (exponentially distributed)."""
    vel_sigma: float = 0.02
    """Standard deviation of the velocity-estimate error, white [m/s]."""
    extpos_sigma: float = 0.002
    """Position-estimate error while external positions (motion capture) arrive [m]."""
    battery_capacity_as: float = 250 * 3.6
    """Capacity [A s] (250 mAh)."""
    hover_current_a: float = 2.1
    """Current drawn while flying [A] (about 7 minutes of flight on a full battery)."""
    idle_current_a: float = 0.1
    """Current drawn with the motors off [A]."""
    internal_resistance_ohm: float = 0.12
    """Voltage sag per ampere [V/A]."""


class QuadBatch:
    """State and dynamics of ``n`` quadrotors. Arrays are ``[n, 3]`` (world frame, z up, SI units)."""

    def __init__(self, n: int, params: QuadParams, start_positions: np.ndarray, seed: int) -> None:
        self.params = params
        self.pos = np.array(start_positions, dtype=np.float64).reshape(n, 3)
        self.vel = np.zeros((n, 3))
        self.yaw_deg = np.zeros(n)
        self.charge_as = np.full(n, params.battery_capacity_as)
        self._rng = np.random.default_rng(seed)
        self._sigma = np.array([params.lps_sigma_xy, params.lps_sigma_xy, params.lps_sigma_z])
        self._est_err = self._sigma * self._rng.standard_normal((n, 3))
        self.estimator = PositionEstimator(n, params, self._rng)
        self._estimator_dt = 0.0

    @property
    def n(self) -> int:
        return self.pos.shape[0]

    def step(self, dt: float, v_des: np.ndarray, yaw_rate_deg: np.ndarray, motors_on: np.ndarray,
             coasting: np.ndarray | None = None, extpos_fresh: np.ndarray | None = None) -> None:
        """Advance ``dt`` seconds. ``motors_on`` [n] bool; where False the drone falls and ``v_des`` is ignored.
        ``coasting`` [n] bool: horizontal control off (the firmware's level-out): only drag acts
        horizontally. ``extpos_fresh`` [n] bool: external positions reach the estimator."""
        p = self.params
        accel = (v_des - self.vel) / p.tau
        norm = np.linalg.norm(accel, axis=1, keepdims=True)
        accel *= np.minimum(1.0, p.max_accel / np.maximum(norm, 1e-9))
        if coasting is not None and coasting.any():
            accel[coasting, :2] = -p.drag_xy * self.vel[coasting, :2]
        accel = np.where(motors_on[:, None], accel, np.array([0.0, 0.0, -GRAVITY]))
        self.vel += accel * dt
        self._limit_speed(motors_on)
        self.pos += self.vel * dt
        self._ground_contact(motors_on)
        self.yaw_deg = np.where(motors_on, (self.yaw_deg + yaw_rate_deg * dt + 180.0) % 360.0 - 180.0,
                                self.yaw_deg)
        current = np.where(motors_on, p.hover_current_a, p.idle_current_a)
        self.charge_as = np.maximum(self.charge_as - current * dt, 0.0)
        self._step_estimate_error(dt)
        self._estimator_dt += dt
        if self._estimator_dt >= 0.999 / PREDICT_RATE_HZ:  # the Kalman filter predicts at 100 Hz
            self.estimator.step(self._estimator_dt,
                                np.zeros(self.n, dtype=bool) if extpos_fresh is None else extpos_fresh)
            self._estimator_dt = 0.0

    def _limit_speed(self, motors_on: np.ndarray) -> None:
        p = self.params
        hspeed = np.linalg.norm(self.vel[:, :2], axis=1)
        scale = np.where(motors_on, np.minimum(1.0, p.max_speed_xy / np.maximum(hspeed, 1e-9)), 1.0)
        self.vel[:, :2] *= scale[:, None]
        self.vel[:, 2] = np.where(motors_on, np.clip(self.vel[:, 2], -p.max_speed_z, p.max_speed_z),
                                  self.vel[:, 2])

    def _ground_contact(self, motors_on: np.ndarray) -> None:
        on_ground = self.pos[:, 2] <= self.params.ground_z
        self.pos[on_ground, 2] = self.params.ground_z
        self.vel[on_ground, 2] = np.maximum(self.vel[on_ground, 2], 0.0)
        # Friction: a drone resting on the floor (motors off, or not climbing) does not slide.
        resting = on_ground & (~motors_on | (self.vel[:, 2] <= 0.0))
        self.vel[resting] = 0.0

    def _step_estimate_error(self, dt: float) -> None:
        decay = math.exp(-dt / self.params.lps_corr_time)
        drive = math.sqrt(1.0 - decay * decay)
        self._est_err = self._est_err * decay + self._sigma * drive * self._rng.standard_normal(self._est_err.shape)

    def reset_estimate_error(self, i: int) -> None:
        """A fresh estimator: a new draw of the error process, its variance back to the initial one."""
        self._est_err[i] = self._sigma * self._rng.standard_normal(3)
        self.estimator.reset(i)

    def position_variance(self, i: int) -> tuple[float, float, float]:
        """kalman.varPX/PY/PZ [m^2] of drone ``i``."""
        return tuple(float(v) for v in self.estimator.p_pos[i])

    def estimated_position(self, i: int, extpos_fresh: bool, extpos: np.ndarray | None = None,
                           extpos_age: float = 0.0) -> np.ndarray:
        """Position as the onboard Kalman filter reports it: truth plus correlated LPS-like error, outliers and
        the drift of a dropout, or, while external positions (motion capture) arrive, the latest one
        propagated by the velocity plus a small error (the filter trusts extpos far more than its own
        prediction)."""
        small = self._est_err[i] * (self.params.extpos_sigma / self.params.lps_sigma_xy)
        if extpos_fresh and extpos is not None:
            return np.asarray(extpos, dtype=float) + self.vel[i] * extpos_age + small
        if extpos_fresh:
            return self.pos[i] + small
        return self.pos[i] + self._est_err[i] + self.estimator.offset[i]

    def estimated_velocity(self, i: int) -> np.ndarray:
        return self.vel[i] + self.params.vel_sigma * self._rng.standard_normal(3)

    def battery_voltage(self, i: int, motors_on: bool) -> float:
        """Terminal voltage [V]: the LiPo's resting voltage at its state of charge (the firmware's charge
        curve, with its knee below 10 %) less the sag under the current drawn."""
        p = self.params
        current = p.hover_current_a if motors_on else p.idle_current_a
        return lipo_resting_voltage(self.charge_as[i] / p.battery_capacity_as) - p.internal_resistance_ohm * current


class PositionEstimator:
    """The Loco Positioning estimate's departures from the truth and the Kalman filter's position variance,
    per drone and axis.

    The variance is a constant-velocity Kalman filter's, run as the firmware runs it
    (``src/modules/src/kalman_core/kalman_core.c``): prediction adds ``(procNoiseAcc * dt)^2`` to the
    velocity variance at 100 Hz and carries it into the position variance; every measurement update pulls the
    position variance down; entries are bounded by MAX_COVARIANCE. The measurement noise is chosen so that
    the steady state is ``lps_sigma**2``, the variance of the simulated error. During a dropout there are no
    updates: the variance grows (past the ground station's 0.01 m^2 limit about 0.6 s in vertically, where
    procNoiseAcc_z is 1.0, about 1.3 s in horizontally) and the estimate drifts by a velocity error that
    random-walks with the same process noise.
    """

    def __init__(self, n: int, params: QuadParams, rng: np.random.Generator) -> None:
        self.params, self._rng = params, rng
        sigma = np.array([params.lps_sigma_xy, params.lps_sigma_xy, params.lps_sigma_z])
        self._target = sigma**2
        self._q = np.array([PROC_NOISE_ACC_XY, PROC_NOISE_ACC_XY, PROC_NOISE_ACC_Z]) ** 2 / PREDICT_RATE_HZ
        """Velocity variance added per second of prediction [m^2/s^3]."""
        # Steady state of the continuous filter: P_pos = sqrt(2) q^(1/4) r^(3/4) for measurement density r.
        self._r_density = (self._target / (math.sqrt(2.0) * self._q**0.25)) ** (4.0 / 3.0)
        self.p_pos = np.tile(self._target, (n, 1))
        self.p_pv = np.tile(np.sqrt(self._q * self._r_density), (n, 1))
        self.p_vel = np.tile(math.sqrt(2.0) * self._q**0.75 * self._r_density**0.25, (n, 1))
        self.offset = np.zeros((n, 3))
        """Outliers plus dropout drift [m], added to the estimate."""
        self._drift_vel = np.zeros((n, 3))
        self._outage_left = np.zeros(n)
        """Seconds of dropout left per drone (0: measurements arrive)."""

    def outage(self, i: int, seconds: float) -> None:
        """No positioning measurement reaches drone ``i`` for ``seconds`` (failure injection)."""
        self._outage_left[i] = max(self._outage_left[i], float(seconds))

    def measuring(self) -> np.ndarray:
        return self._outage_left <= 0.0

    def reset(self, i: int) -> None:
        """kalman.resetEstimation: stdDevInitialPosition (100 m, bounded) and stdDevInitialVelocity (0.01)."""
        self.p_pos[i], self.p_pv[i], self.p_vel[i] = MAX_COVARIANCE, 0.0, 1e-4
        self.offset[i], self._drift_vel[i] = 0.0, 0.0

    def step(self, dt: float, extpos_fresh: np.ndarray) -> None:
        p, rng, n = self.params, self._rng, len(self.p_pos)
        was = self.measuring()
        u = rng.random(2 * n)  # one draw per step for the dropout and outlier onsets (the sim runs at 200 Hz)
        starts = was & (u[:n] < p.lps_dropout_rate * dt)
        if starts.any():
            self._outage_left[starts] = rng.exponential(p.lps_dropout_mean_s, int(starts.sum()))
        if (self._outage_left > 0).any():
            self._outage_left = np.maximum(self._outage_left - dt, 0.0)
        meas = self.measuring() | extpos_fresh
        # prediction (a constant-velocity model per axis), then the update where positions arrive
        self.p_pos += 2.0 * dt * self.p_pv + dt * dt * self.p_vel
        self.p_pv += dt * self.p_vel
        self.p_vel += self._q * dt
        r = self._r_density / dt
        if extpos_fresh.any():
            r = np.where(extpos_fresh[:, None], 1e-4, r)  # extpos: locSrv.extPosStdDev 0.01 m
        k = self.p_pos / (self.p_pos + r)
        if meas.all():
            self.p_vel -= k * self.p_pv
            self.p_pv *= 1.0 - k
            self.p_pos *= 1.0 - k
        else:
            upd = meas[:, None]
            self.p_vel = np.where(upd, self.p_vel - k * self.p_pv, self.p_vel)
            self.p_pv = np.where(upd, (1.0 - k) * self.p_pv, self.p_pv)
            self.p_pos = np.where(upd, (1.0 - k) * self.p_pos, self.p_pos)
            for a in (self.p_pos, self.p_pv, self.p_vel):
                np.clip(a, -MAX_COVARIANCE, MAX_COVARIANCE, out=a)
        self._step_offset(dt, meas, was, u[n:])

    def _step_offset(self, dt: float, meas: np.ndarray, was: np.ndarray, u: np.ndarray) -> None:
        """The estimate's departures: drift while dead-reckoning, outliers while measuring; both fade once
        measurements are back."""
        p, rng, n = self.params, self._rng, len(self.p_pos)
        self.offset *= math.exp(-dt / p.lps_corr_time)
        lost = ~meas
        if lost.any():
            onset = lost & was
            if onset.any():
                self._drift_vel[onset] = np.sqrt(self.p_vel[onset]) * rng.standard_normal((int(onset.sum()), 3))
            walk = self._drift_vel[lost] + np.sqrt(self._q * dt) * rng.standard_normal((int(lost.sum()), 3))
            self._drift_vel[lost] = walk
            self.offset[lost] = self.offset[lost] / math.exp(-dt / p.lps_corr_time) + walk * dt
        self._drift_vel[meas] = 0.0
        hit = meas & (u < p.lps_outlier_rate * dt)
        if hit.any():
            direction = rng.standard_normal((int(hit.sum()), 3))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            self.offset[hit] += direction * rng.exponential(p.lps_outlier_m, (int(hit.sum()), 1))


def smooth_segment(tau: float) -> tuple[float, float]:
    """7th-order rest-to-rest blend s(tau) and ds/dtau on tau in [0, 1] (zero velocity, acceleration and
    jerk at both ends, like the firmware planner's go_to from hover)."""
    t = min(max(tau, 0.0), 1.0)
    s = t**4 * (35.0 - 84.0 * t + 70.0 * t * t - 20.0 * t**3)
    ds = t**3 * (140.0 - 420.0 * t + 420.0 * t * t - 140.0 * t**3)
    return s, ds


def smooth_segment_dd(tau: float) -> float:
    """d^2 s / d tau^2 of ``smooth_segment`` (zero outside [0, 1])."""
    if not 0.0 <= tau <= 1.0:
        return 0.0
    t = tau
    return t * t * (420.0 - 1680.0 * t + 2100.0 * t * t - 840.0 * t**3)


@dataclass(frozen=True)
class Segment:
    """One planned high-level-commander motion from ``start`` to ``end``."""

    t0: float
    """Start time [s, simulator clock]."""
    duration: float
    """[s]"""
    start: tuple[float, float, float]
    """[m]"""
    end: tuple[float, float, float]
    """[m]"""
    linear: bool = False
    """Straight-line constant-speed interpolation instead of the smooth polynomial."""

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Reference position [m] and velocity [m/s] at time ``t``."""
        start, end = np.asarray(self.start), np.asarray(self.end)
        if self.duration <= 0.0:
            return end.copy(), np.zeros(3)
        tau = (t - self.t0) / self.duration
        if self.linear:
            s, ds = min(max(tau, 0.0), 1.0), (1.0 if 0.0 <= tau <= 1.0 else 0.0)
        else:
            s, ds = smooth_segment(tau)
        return start + (end - start) * s, (end - start) * ds / self.duration

    def acceleration(self, t: float) -> np.ndarray:
        """Reference acceleration [m/s^2] at time ``t`` (the planner's feed-forward term)."""
        if self.duration <= 0.0 or self.linear:
            return np.zeros(3)
        dd = smooth_segment_dd((t - self.t0) / self.duration)
        return (np.asarray(self.end) - np.asarray(self.start)) * dd / self.duration**2

    def finished(self, t: float) -> bool:
        return t >= self.t0 + self.duration
