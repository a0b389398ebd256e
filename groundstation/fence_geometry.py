"""The geofence's per-setpoint geometry, compiled with numba (``nogil``: the links' receive threads that run it
do not hold the interpreter's lock while they do).

Every setpoint of every drone passes ``check_position`` and ``limit_velocity`` (``safety.Geofence``); written
with numpy calls on 2- and 3-vectors they cost tens of microseconds of the ground station's GIL each and were
its largest item on the setpoint path (py-spy of the 12-drone demo). The kernels here are the same
arithmetic on scalars, in the same order; ``tests/fence_reference.py`` keeps the numpy version they replaced,
and ``tests/test_fence_geometry.py`` checks both agree, and agree with shapely, on random fences and points.

The fence arrives as one packed float64 vector (``pack``): one array to pass instead of ten keeps numba's
call overhead to about a microsecond. Layout: ``[n, m, k, z_lo, z_hi, z_min, z_max, lo_x, lo_y, hi_x, hi_y]``
then the fence polygon's outward normals ``[n, 2]`` and offsets ``[n]``, the safe polygon's corners ``[m, 2]``,
normals ``[m, 2]`` and offsets ``[m]``, the keep-out centres ``[k, 2]``, radii ``[k]`` and grown radii ``[k]``.

Status codes (``check``) follow ``fence.FenceStatus``: 0 inside, 1 margin, 2 low, 3 outside.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

TOL = 1e-9
"""Slack [m] when testing membership of points computed exactly on a boundary."""
PARALLEL = 1e-12
"""Ray directions closer than this to parallel with a boundary plane are treated as parallel."""
BRAKE_SLACK = 1e-6
"""Distance [m] kept back from a boundary by the velocity limit, against rounding."""
HEADER = 11
INSIDE, MARGIN, LOW, OUTSIDE = 0, 1, 2, 3


def pack(normals: np.ndarray, offsets: np.ndarray, inner: np.ndarray, inner_normals: np.ndarray,
         inner_offsets: np.ndarray, centres: np.ndarray, radii: np.ndarray, grown: np.ndarray, z_lo: float,
         z_hi: float, z_min: float, z_max: float, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The fence's geometry as the one float64 vector the kernels take (layout in the module's docstring)."""
    head = [len(normals), len(inner), len(radii), z_lo, z_hi, z_min, z_max, lo[0], lo[1], hi[0], hi[1]]
    parts = [np.asarray(head, dtype=float), normals.ravel(), offsets, inner.ravel(), inner_normals.ravel(),
             inner_offsets, centres.ravel(), radii, grown]
    g = np.ascontiguousarray(np.concatenate([np.asarray(a, dtype=float).ravel() for a in parts]))
    g.setflags(write=False)
    return g


# -- the packed fence's parts (indices into g) ------------------------------------------------------------

@njit(cache=True, nogil=True)
def _starts(g):
    n, m, k = int(g[0]), int(g[1]), int(g[2])
    nrm = HEADER
    off = nrm + 2 * n
    inner = off + n
    inn = inner + 2 * m
    ino = inn + 2 * m
    cen = ino + m
    rad = cen + 2 * k
    grown = rad + k
    return n, m, k, nrm, off, inner, inn, ino, cen, rad, grown


@njit(cache=True, nogil=True)
def _in_polygon(g, count, nrm, off, x, y, tol):
    for i in range(count):
        if g[nrm + 2 * i] * x + g[nrm + 2 * i + 1] * y > g[off + i] + tol:
            return False
    return True


@njit(cache=True, nogil=True)
def _outside_circles(g, k, cen, rad, x, y, tol):
    for i in range(k):
        if math.hypot(x - g[cen + 2 * i], y - g[cen + 2 * i + 1]) < g[rad + i] - tol:
            return False
    return True


@njit(cache=True, nogil=True)
def in_safe_xy(g, x, y, tol):
    """Whether ``(x, y)`` lies in the horizontal safe set (within ``tol`` [m])."""
    n, m, k, nrm, off, inner, inn, ino, cen, rad, grown = _starts(g)
    return _in_polygon(g, m, inn, ino, x, y, tol) and _outside_circles(g, k, cen, grown, x, y, tol)


@njit(cache=True, nogil=True)
def in_safe_set(g, p, tol):
    """Whether ``p`` [3] (finite) lies in the safe set (within ``tol`` [m])."""
    return g[3] - tol <= p[2] <= g[4] + tol and in_safe_xy(g, p[0], p[1], tol)


@njit(cache=True, nogil=True)
def check(g, p):
    """Where finite ``p`` [3] lies: INSIDE, MARGIN, LOW or OUTSIDE (``fence.check_position``)."""
    n, m, k, nrm, off, inner, inn, ino, cen, rad, grown = _starts(g)
    x, y, z = p[0], p[1], p[2]
    if not _in_polygon(g, n, nrm, off, x, y, 0.0) or not _outside_circles(g, k, cen, rad, x, y, 0.0) \
            or z > g[6]:
        return OUTSIDE
    if z < g[5]:
        return LOW
    if in_safe_xy(g, x, y, 0.0) and g[3] <= z <= g[4]:
        return INSIDE
    return MARGIN


# -- the nearest safe point ----------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _try(g, qx, qy, x, y, best):
    """Keep candidate ``q`` in ``best`` ``[x, y, distance, found]`` when it is safe and strictly nearer."""
    if in_safe_xy(g, qx, qy, TOL):
        d = math.hypot(qx - x, qy - y)
        if d < best[2]:
            best[0], best[1], best[2], best[3] = qx, qy, d, 1.0


@njit(cache=True, nogil=True)
def _segment_circle(g, best, ax, ay, bx, by, cx, cy, r, x, y):
    dx, dy = bx - ax, by - ay
    wx, wy = ax - cx, ay - cy
    qa = dx * dx + dy * dy
    qb = 2 * (wx * dx + wy * dy)
    qc = wx * wx + wy * wy - r * r
    disc = qb * qb - 4 * qa * qc
    if disc < 0:
        return
    s = math.sqrt(disc)
    for t in ((-qb - s) / (2 * qa), (-qb + s) / (2 * qa)):
        if 0.0 <= t <= 1.0:
            _try(g, ax + t * dx, ay + t * dy, x, y, best)


@njit(cache=True, nogil=True)
def clamp_xy(g, x, y, out):
    """The nearest point of the horizontal safe set to finite ``(x, y)``, into ``out`` [2]; False when the set is
    empty.

    The set is bounded by the safe polygon's edges and the grown circles, so its nearest point is a
    projection onto one of those pieces or a corner where two meet; every such candidate that lies in the set
    is tried, in a fixed order, and the first of the nearest wins."""
    if in_safe_xy(g, x, y, TOL):
        out[0], out[1] = x, y
        return True
    n, m, k, nrm, off, inner, inn, ino, cen, rad, grown = _starts(g)
    best = np.array([0.0, 0.0, math.inf, 0.0])
    for i in range(m):  # corners
        _try(g, g[inner + 2 * i], g[inner + 2 * i + 1], x, y, best)
    for i in range(m):  # projections onto the edges
        j = (i + 1) % m
        ax, ay = g[inner + 2 * i], g[inner + 2 * i + 1]
        abx, aby = g[inner + 2 * j] - ax, g[inner + 2 * j + 1] - ay
        t = ((x - ax) * abx + (y - ay) * aby) / (abx * abx + aby * aby)
        t = min(max(t, 0.0), 1.0)
        _try(g, ax + t * abx, ay + t * aby, x, y, best)
    for c in range(k):
        cx, cy, r = g[cen + 2 * c], g[cen + 2 * c + 1], g[grown + c]
        dx, dy = x - cx, y - cy
        dn = math.hypot(dx, dy)
        if dn > 1e-12:  # the projection onto the circle, a hair outside
            _try(g, cx + dx * (r / dn) * (1 + 1e-12), cy + dy * (r / dn) * (1 + 1e-12), x, y, best)
        else:  # at the centre every direction is nearest: eight of them
            for a in range(8):
                ang = a * math.pi / 4
                _try(g, cx + r * (1 + 1e-12) * math.cos(ang), cy + r * (1 + 1e-12) * math.sin(ang), x, y, best)
        for i in range(m):  # where the circle crosses the polygon's edges
            j = (i + 1) % m
            _segment_circle(g, best, g[inner + 2 * i], g[inner + 2 * i + 1], g[inner + 2 * j],
                            g[inner + 2 * j + 1], cx, cy, r, x, y)
    for a in range(k):  # where two circles cross
        for b in range(a + 1, k):
            ax, ay, ra = g[cen + 2 * a], g[cen + 2 * a + 1], g[grown + a]
            bx, by, rb = g[cen + 2 * b], g[cen + 2 * b + 1], g[grown + b]
            ex, ey = bx - ax, by - ay
            d = math.hypot(ex, ey)
            if d < 1e-12 or d > ra + rb or d < abs(ra - rb):
                continue
            h0 = (ra * ra - rb * rb + d * d) / (2 * d)
            h = math.sqrt(max(ra * ra - h0 * h0, 0.0))
            mx, my = ax + h0 * ex / d, ay + h0 * ey / d
            px, py = -ey / d, ex / d
            _try(g, mx + h * px, my + h * py, x, y, best)
            _try(g, mx - h * px, my - h * py, x, y, best)
    if best[3] == 0.0:
        return False
    out[0], out[1] = best[0], best[1]
    return True


@njit(cache=True, nogil=True)
def clamp_position(g, p, out):
    """The nearest point of the safe set to finite ``p`` [3], pulled in from absurd distances first, into
    ``out`` [3]; False when the horizontal safe set is empty (the fence refuses such configs)."""
    x = min(max(p[0], g[7]), g[9])
    y = min(max(p[1], g[8]), g[10])
    if not clamp_xy(g, x, y, out):
        return False
    out[2] = min(max(p[2], g[3]), g[4])
    return True


# -- the velocity rule ---------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def free_distance(g, px, py, pz, ux, uy, uz):
    """Distance [m] from ``p`` (in the safe set) along unit vector ``u`` to the safe set's boundary."""
    n, m, k, nrm, off, inner, inn, ino, cen, rad, grown = _starts(g)
    t = math.inf
    if uz > PARALLEL:
        t = min(t, (g[4] - pz) / uz)
    elif uz < -PARALLEL:
        t = min(t, (g[3] - pz) / uz)
    for i in range(m):
        nx, ny = g[inn + 2 * i], g[inn + 2 * i + 1]
        nu = nx * ux + ny * uy
        if nu > PARALLEL:  # nearly parallel planes are met far beyond the others, which bound the ray
            t = min(t, (g[ino + i] - (nx * px + ny * py)) / nu)
    qa = ux * ux + uy * uy
    if qa > 0:
        for c in range(k):
            wx, wy = px - g[cen + 2 * c], py - g[cen + 2 * c + 1]
            r = g[grown + c]
            b = wx * ux + wy * uy
            cc = (wx * wx + wy * wy) - r * r
            if cc <= 0:
                if b < 0:  # on or inside the grown circle and heading further in
                    t = 0.0
                continue
            disc = b * b - qa * cc
            if b < 0 and disc > 0:
                t = min(t, (-b - math.sqrt(disc)) / qa)
    return max(t, 0.0)


@njit(cache=True, nogil=True)
def max_safe_speed(distance, dt, max_decel, coast_time):
    """Largest speed s [m/s] with ``s dt + s^2 / (2 max_decel) <= distance`` and ``s coast_time <= distance``."""
    if distance <= 0:
        return 0.0
    if math.isinf(distance):
        return math.inf
    brake = max_decel * (-dt + math.sqrt(dt * dt + 2.0 * distance / max_decel))
    return min(brake, distance / coast_time) if coast_time > 0 else brake


@njit(cache=True, nogil=True)
def limit_velocity(g, p, w, dt, max_speed, max_decel, coast_time, far, out):
    """``safety.limit_velocity`` for finite ``p`` [3] and ``w`` [3] and finite ``dt >= 0``, into ``out`` [3]
    (zeros when the drone must hover)."""
    out[0], out[1], out[2] = 0.0, 0.0, 0.0
    scale = max(abs(w[0]), abs(w[1]), abs(w[2]))
    if scale <= 0:
        return
    sx, sy, sz = w[0] / scale, w[1] / scale, w[2] / scale  # scaled first: huge components cannot overflow
    norm = math.sqrt(sx * sx + sy * sy + sz * sz)
    ux, uy, uz = sx / norm, sy / norm, sz / norm
    speed = min(scale * norm, max_speed)
    if in_safe_set(g, p, TOL):
        d = free_distance(g, p[0], p[1], p[2], ux, uy, uz) - BRAKE_SLACK
        s = min(speed, max_safe_speed(d, dt, max_decel, coast_time))
        if s > 0:
            out[0], out[1], out[2] = ux * s, uy * s, uz * s
        return
    q = np.empty(3)
    pin = np.empty(3)
    pin[0] = min(max(p[0], g[7]), g[9])
    pin[1] = min(max(p[1], g[8]), g[10])
    pin[2] = min(max(p[2], -far), far)
    if not clamp_position(g, pin, q):
        return
    tx, ty, tz = q[0] - pin[0], q[1] - pin[1], q[2] - pin[2]
    dist = math.sqrt(tx * tx + ty * ty + tz * tz)
    if dist <= TOL:
        return
    qx, qy, qz = tx / dist, ty / dist, tz / dist
    s = min(speed * (ux * qx + uy * qy + uz * qz), max_safe_speed(dist, dt, max_decel, coast_time))
    if s > 0:
        out[0], out[1], out[2] = qx * s, qy * s, qz * s
