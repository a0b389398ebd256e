"""Physics of the simulated Crazyflies: a batch of position-controlled quadrotors.

Pure numpy, batch-first (``[n_drones, 3]``), no sockets and no clocks: the caller passes ``dt``. The
firmware logic in ``firmware.py`` turns setpoints into a desired velocity per drone; this module turns
desired velocities into motion (first-order response, acceleration and speed limits, gravity when the
motors are off, ground contact), adds Loco-Positioning-like estimation noise and drains the batteries.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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
    ground_z: float = 0.0
    """Floor height [m]."""
    lps_sigma_xy: float = 0.03
    """Standard deviation of the horizontal position-estimate error, like the Loco Positioning System [m]."""
    lps_sigma_z: float = 0.04
    """Standard deviation of the vertical position-estimate error [m]."""
    lps_corr_time: float = 0.3
    """Correlation time of the position-estimate error (Gauss-Markov) [s]."""
    vel_sigma: float = 0.02
    """Standard deviation of the velocity-estimate error, white [m/s]."""
    extpos_sigma: float = 0.002
    """Position-estimate error while external positions (motion capture) arrive [m]."""
    battery_full_v: float = 4.2
    """Open-circuit voltage of a full battery [V]."""
    battery_empty_v: float = 3.0
    """Open-circuit voltage of an empty battery [V]."""
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
        self._est_err = np.zeros((n, 3))
        self._rng = np.random.default_rng(seed)
        self._sigma = np.array([params.lps_sigma_xy, params.lps_sigma_xy, params.lps_sigma_z])

    @property
    def n(self) -> int:
        return self.pos.shape[0]

    def step(self, dt: float, v_des: np.ndarray, yaw_rate_deg: np.ndarray, motors_on: np.ndarray) -> None:
        """Advance ``dt`` seconds. ``motors_on`` [n] bool; where False the drone falls and ``v_des`` is ignored."""
        p = self.params
        accel = (v_des - self.vel) / p.tau
        norm = np.linalg.norm(accel, axis=1, keepdims=True)
        accel *= np.minimum(1.0, p.max_accel / np.maximum(norm, 1e-9))
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
        """A fresh estimator starts from a new draw of the error process."""
        self._est_err[i] = self._sigma * self._rng.standard_normal(3)

    def estimated_position(self, i: int, extpos_fresh: bool, extpos: np.ndarray | None = None,
                           extpos_age: float = 0.0) -> np.ndarray:
        """Position as the onboard Kalman filter reports it: truth plus correlated LPS-like error, or, while
        external positions (motion capture) arrive, the latest one propagated by the velocity plus a small
        error (the filter trusts extpos far more than its own prediction)."""
        small = self._est_err[i] * (self.params.extpos_sigma / self.params.lps_sigma_xy)
        if extpos_fresh and extpos is not None:
            return np.asarray(extpos, dtype=float) + self.vel[i] * extpos_age + small
        if extpos_fresh:
            return self.pos[i] + small
        return self.pos[i] + self._est_err[i]

    def estimated_velocity(self, i: int) -> np.ndarray:
        return self.vel[i] + self.params.vel_sigma * self._rng.standard_normal(3)

    def battery_voltage(self, i: int, motors_on: bool) -> float:
        p = self.params
        soc = self.charge_as[i] / p.battery_capacity_as
        current = p.hover_current_a if motors_on else p.idle_current_a
        return p.battery_empty_v + (p.battery_full_v - p.battery_empty_v) * soc - p.internal_resistance_ohm * current


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
