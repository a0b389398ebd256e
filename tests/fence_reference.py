"""The geofence's geometry as it was written before it was compiled (``groundstation/fence.py`` and
``safety.py`` at 16b937c, numpy on 2- and 3-vectors), kept as the reference that
``groundstation.fence_geometry`` is checked against (``tests/test_fence_geometry.py``) and timed beside
(``tests/benchmarks/test_bench_fence.py``). Reads the same ``fence.Geometry`` arrays; nothing else changed.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from groundstation.fence import FAR, PARALLEL, TOL, FenceConfig, FenceStatus, Geometry, as_point, geometry

_BRAKE_SLACK = 1e-6


def _in_polygon(normals: np.ndarray, offsets: np.ndarray, xy: np.ndarray, tol: float = TOL) -> bool:
    return bool(np.all(normals @ xy <= offsets + tol))


def _outside_circles(centres: np.ndarray, radii: np.ndarray, xy: np.ndarray, tol: float = TOL) -> bool:
    if len(radii) == 0:
        return True
    d = np.hypot(xy[0] - centres[:, 0], xy[1] - centres[:, 1])
    return bool(np.all(d >= radii - tol))


def _in_safe_xy(g: Geometry, xy: np.ndarray, tol: float = TOL) -> bool:
    return _in_polygon(g.inner_normals, g.inner_offsets, xy, tol) and _outside_circles(g.centres, g.grown, xy, tol)


def _segment_closest(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    ab = b - a
    t = float(np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0))
    return a + t * ab


def _segment_circle(a: np.ndarray, b: np.ndarray, c: np.ndarray, r: float) -> list[np.ndarray]:
    d = b - a
    w = a - c
    qa, qb, qc = d @ d, 2 * (w @ d), w @ w - r * r
    disc = qb * qb - 4 * qa * qc
    if disc < 0:
        return []
    s = math.sqrt(disc)
    return [a + t * d for t in ((-qb - s) / (2 * qa), (-qb + s) / (2 * qa)) if 0.0 <= t <= 1.0]


def _circle_circle(c0: np.ndarray, r0: float, c1: np.ndarray, r1: float) -> list[np.ndarray]:
    d = float(np.hypot(*(c1 - c0)))
    if d < 1e-12 or d > r0 + r1 or d < abs(r0 - r1):
        return []
    a = (r0 * r0 - r1 * r1 + d * d) / (2 * d)
    h = math.sqrt(max(r0 * r0 - a * a, 0.0))
    m = c0 + a * (c1 - c0) / d
    perp = np.array([-(c1 - c0)[1], (c1 - c0)[0]]) / d
    return [m + h * perp, m - h * perp]


def _clamp_xy(g: Geometry, xy: np.ndarray) -> np.ndarray | None:
    """The nearest point of the horizontal safe set to ``xy`` (finite), or None when the set is empty.

    The safe set is bounded by the inner polygon's edges and the grown circles, so its nearest point is a
    projection onto one of those pieces or a corner where two of them meet; every such candidate that lies
    in the set is tried and the nearest wins."""
    if _in_safe_xy(g, xy):
        return xy
    inner = g.inner
    cands: list[np.ndarray] = [v for v in inner]
    edges = [(inner[i], inner[(i + 1) % len(inner)]) for i in range(len(inner))]
    cands += [_segment_closest(a, b, xy) for a, b in edges]
    for c, r in zip(g.centres, g.grown):
        d = xy - c
        n = float(np.hypot(*d))
        if n > 1e-12:
            cands.append(c + d * (r / n) * (1 + 1e-12))
        else:
            cands += [c + r * (1 + 1e-12) * np.array([math.cos(a), math.sin(a)]) for a in np.arange(8) * math.pi / 4]
        for a, b in edges:
            cands += _segment_circle(a, b, c, r)
    k = len(g.radii)
    for i in range(k):
        for j in range(i + 1, k):
            cands += _circle_circle(g.centres[i], g.grown[i], g.centres[j], g.grown[j])
    best, best_d = None, math.inf
    for q in cands:
        if _in_safe_xy(g, q):
            dq = float(np.hypot(*(q - xy)))
            if dq < best_d:
                best, best_d = q, dq
    return None if best is None else np.asarray(best, dtype=float)


def check_position(fence: FenceConfig, p: Sequence[float] | np.ndarray | None) -> FenceStatus:
    """Where measured position ``p`` [m] is relative to the fence. Non-finite or missing counts as OUTSIDE."""
    g = geometry(fence)
    a = as_point(p)
    if a is None:
        return FenceStatus.OUTSIDE
    xy = a[:2]
    if (not _in_polygon(g.normals, g.offsets, xy, 0.0) or not _outside_circles(g.centres, g.radii, xy, 0.0)
            or a[2] > fence.z_max):
        return FenceStatus.OUTSIDE
    if a[2] < fence.z_min:
        return FenceStatus.LOW
    if _in_safe_xy(g, xy, 0.0) and g.z_lo <= a[2] <= g.z_hi:
        return FenceStatus.INSIDE
    return FenceStatus.MARGIN


def in_safe_set(fence: FenceConfig, p: Sequence[float] | np.ndarray, tol: float = TOL) -> bool:
    """Whether ``p`` [m] lies in the safe set (within ``tol`` [m])."""
    g = geometry(fence)
    a = as_point(p)
    return a is not None and g.z_lo - tol <= a[2] <= g.z_hi + tol and _in_safe_xy(g, a[:2], tol)


def clamp_position(fence: FenceConfig, p: Sequence[float] | np.ndarray | None,
                   fallback: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """The nearest point of the safe set to position setpoint ``p`` [m].

    A ``p`` that is missing or has any non-finite coordinate is replaced by ``fallback`` (pass the last safe
    setpoint or the drone's measured position), itself clamped; with no usable fallback the result is
    ``fence.home``. Coordinates absurdly far away are pulled in first so that nothing overflows."""
    g = geometry(fence)
    a = as_point(p)
    if a is None:
        a = as_point(fallback)
        if a is None:
            return fence.home
    a[:2] = np.clip(a[:2], g.lo, g.hi)
    xy = _clamp_xy(g, a[:2])
    if xy is None:  # unreachable: the fence refuses configs without a safe set
        return fence.home
    return np.array([xy[0], xy[1], min(max(a[2], g.z_lo), g.z_hi)])


def free_distance(fence: FenceConfig, p: np.ndarray, u: np.ndarray) -> float:
    """Distance [m] from ``p`` (in the safe set) along unit vector ``u`` to the safe set's boundary."""
    g = geometry(fence)
    t = math.inf
    if u[2] > PARALLEL:
        t = min(t, (g.z_hi - p[2]) / u[2])
    elif u[2] < -PARALLEL:
        t = min(t, (g.z_lo - p[2]) / u[2])
    uxy = u[:2]
    for n, c in zip(g.inner_normals, g.inner_offsets):
        nu = float(n @ uxy)
        if nu > PARALLEL:  # nearly parallel planes are met far beyond the others, which bound the ray
            t = min(t, (c - float(n @ p[:2])) / nu)
    qa = float(uxy @ uxy)
    if qa > 0:
        for c, r in zip(g.centres, g.grown):
            w = p[:2] - c
            b = float(w @ uxy)
            cc = float(w @ w) - r * r
            if cc <= 0:
                if b < 0:  # on or inside the grown circle and heading further in
                    t = 0.0
                continue
            disc = b * b - qa * cc
            if b < 0 and disc > 0:
                t = min(t, (-b - math.sqrt(disc)) / qa)
    return max(t, 0.0)


def max_safe_speed(distance: float, dt: float, max_decel: float, coast_time: float = 0.0) -> float:
    """Largest speed s [m/s] with ``s dt + s^2 / (2 max_decel) <= distance`` and ``s coast_time <= distance``."""
    if distance <= 0:
        return 0.0
    if math.isinf(distance):
        return math.inf
    brake = max_decel * (-dt + math.sqrt(dt * dt + 2.0 * distance / max_decel))
    return min(brake, distance / coast_time) if coast_time > 0 else brake


def limit_velocity(fence: FenceConfig, position: Sequence[float] | np.ndarray | None,
                   v: Sequence[float] | np.ndarray | None, dt: float) -> np.ndarray:
    """Velocity setpoint ``v`` [m/s] cut so that a drone at ``position`` [m] flying it for ``dt`` [s] and then
    braking at ``fence.max_decel``, or flying and coasting on it for ``fence.coast_time``, stays in the safe
    set.

    The direction is kept and only the speed is reduced (to at most ``fence.max_speed``). From a position
    outside the safe set only the part of ``v`` that heads for the nearest safe point is kept, slow enough to
    stop there. Missing or non-finite ``position``, ``v`` or ``dt``, or ``dt < 0``, give zero (hover)."""
    g = geometry(fence)
    zero = np.zeros(3)
    p = as_point(position)
    w = as_point(v)
    if p is None or w is None or not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt >= 0):
        return zero
    scale = float(np.max(np.abs(w)))
    if scale <= 0:
        return zero
    u = w / scale
    u /= float(np.linalg.norm(u))  # scaled first so that huge components cannot overflow
    speed = min(scale * float(np.linalg.norm(w / scale)), fence.max_speed)
    if in_safe_set(fence, p):
        d = free_distance(fence, p, u) - _BRAKE_SLACK
        s = min(speed, max_safe_speed(d, dt, fence.max_decel, fence.coast_time))
        return u * s if s > 0 else zero
    p[:2] = np.clip(p[:2], g.lo, g.hi)
    p[2] = min(max(p[2], -FAR), FAR)
    q = clamp_position(fence, p)
    to_q = q - p
    dist = float(np.linalg.norm(to_q))
    if dist <= TOL:
        return zero
    uq = to_q / dist
    s = min(speed * float(u @ uq), max_safe_speed(dist, dt, fence.max_decel, fence.coast_time))
    return uq * s if s > 0 else zero


def clamp_path(fence: FenceConfig, start: Sequence[float] | np.ndarray | None,
               target: Sequence[float] | np.ndarray | None,
               fallback: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """Position setpoint ``target`` [m] clamped into the safe set and, when the drone's position ``start``
    is known and safe, pulled back along the straight line from ``start`` so that the path there does not
    cut through a keep-out circle or a corner of the margin. Non-finite ``target`` falls back as in
    ``clamp_position``."""
    q = clamp_position(fence, target, fallback if fallback is not None else start)
    s = as_point(start)
    if s is None:
        return q
    if not in_safe_set(fence, s):
        s = clamp_position(fence, s)  # a drone in the margin starts its path from the nearest safe point
    d = q - s
    n = float(np.linalg.norm(d))
    if n <= TOL:
        return q
    free = free_distance(fence, s, d / n) - _BRAKE_SLACK
    if free >= n:
        return q
    return s + d / n * max(free, 0.0)
