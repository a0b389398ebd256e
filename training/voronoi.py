"""Exact Voronoi cells clipped to the square arena: areas and centroids, batched.

The scouts' exploration reward (``E = -max bounded cell area``) needs every env's cells each step, so this is
a numba kernel over all ``B * N`` cells at once, with no per-env Python loop and no scipy/shapely.

Algorithm (one cell, float64 throughout): start from the square ``[-hw, hw]^2`` as a CCW polygon and clip
it (Sutherland-Hodgman) by the bisector half-plane of point ``i`` against each other point ``j``,
``n . x <= n . (p_i + p_j) / 2`` with ``n = (p_j - p_i) / |p_j - p_i|``. Three shortcuts keep it cheap:

- the other points are insertion-sorted by distance and clipped nearest first, so the cell shrinks fast;
- a half-plane that contains every vertex of the current polygon is skipped without rebuilding it;
- the loop stops once half the distance to the next point exceeds the largest distance from ``p_i`` to a
  vertex of the polygon: that bisector, and every farther one, lies outside the polygon.

Area and centroid come from the shoelace formula taken relative to the polygon's first vertex.

Numerical consistency: the bisector of ``(i, j)`` is computed so that the one seen from ``j`` is bitwise
the negation of the one seen from ``i`` (exact IEEE negation, commutative midpoint), so neighbouring cells
share their edge up to the rounding of the clip intersections and the areas sum to ``(2 hw)^2`` to about
1e-15 relative.

Conventions for degenerate inputs:

- Coincident points (exactly equal coordinates) share their common cell: each of the ``m`` copies gets
  ``area / m`` and the centroid of the shared cell. ``N = 1`` or all points identical: the whole square,
  split equally, centroid at the centre.
- Collinear points give strip cells; points on an edge or a corner need nothing special.
- Points outside the square (any finite coordinates) are allowed: the cells of all points partition the
  plane, so clipped to the square they still partition it. A point whose clipped cell is empty gets area 0
  and, as centroid, itself clamped to the square.
- Centroids are clamped to the square, which only ever moves them by rounding.
- NaN or inf anywhere in ``points`` or ``half_width`` is a ``ValueError`` naming the argument.
"""
from __future__ import annotations

import math
import numbers

import numpy as np
from numba import njit, prange

from runtime.geometry import clip_into

__all__ = ["bounded_cell_areas", "bounded_cell_polygons", "bounded_cells"]

# Cells handled by one parallel task: large enough to amortize its scratch buffers, small enough to balance.
_CHUNK = 32
# Below this many cells the parallel launch costs more than it saves.
_SERIAL_CELLS = 128
# Relative margin on the early-stop test, so that rounding never skips a bisector that still cuts.
_STOP_MARGIN = 1.0 + 1e-9


@njit(cache=True, fastmath=False)
def _clip_cell(pts, b, i, hw, key, idx, fv, bx, by):
    """Clip cell ``i`` of env ``b``: returns ``(src, nv, mult)``, its ``nv`` CCW vertices at offset ``src`` of
    ``bx, by`` and how many points share it (coincident copies); the other arguments are scratch.

    ``bx, by`` hold two vertex buffers of ``cap`` slots each, at offsets 0 and ``cap``: each clip
    (``runtime.geometry.clip_into``) reads one and writes the other (offsets, not swapped array variables, which
    would cost reference counting).
    """
    n = pts.shape[1]
    cap = bx.shape[0] // 2
    pix = pts[b, i, 0]
    piy = pts[b, i, 1]
    mult = 1
    m = 0
    for j in range(n):
        if j == i:
            continue
        dx = pts[b, j, 0] - pix
        dy = pts[b, j, 1] - piy
        if dx == 0.0 and dy == 0.0:
            mult += 1
            continue
        d2 = dx * dx + dy * dy
        k = m
        while k > 0 and key[k - 1] > d2:
            key[k] = key[k - 1]
            idx[k] = idx[k - 1]
            k -= 1
        key[k] = d2
        idx[k] = j
        m += 1

    bx[0] = -hw
    by[0] = -hw
    bx[1] = hw
    by[1] = -hw
    bx[2] = hw
    by[2] = hw
    bx[3] = -hw
    by[3] = hw
    src = 0
    nv = 4
    ex = hw + abs(pix)
    ey = hw + abs(piy)
    r2max = ex * ex + ey * ey

    for k in range(m):
        if 0.25 * key[k] > r2max * _STOP_MARGIN:
            break
        j = idx[k]
        qx = pts[b, j, 0]
        qy = pts[b, j, 1]
        dx = qx - pix
        dy = qy - piy
        length = math.sqrt(key[k])
        if not length > 1e-150:
            length = math.hypot(dx, dy)  # dx * dx + dy * dy underflowed
        # Divide (not multiply by 1 / length, which overflows for subnormal lengths); then the bisector seen
        # from j is bitwise the negation of this one, so the two cells agree on which side each vertex is.
        nx = dx / length
        ny = dy / length
        c = nx * (0.5 * (pix + qx)) + ny * (0.5 * (piy + qy))
        fmax = -np.inf
        for v in range(nv):
            f = nx * bx[src + v] + ny * by[src + v] - c
            fv[v] = f
            if f > fmax:
                fmax = f
        if fmax <= 0.0:
            continue
        dst = cap - src
        nv = clip_into(bx, by, src, nv, fv, dst, cap)
        src = dst
        r2max = 0.0
        for v in range(nv):
            ex = bx[src + v] - pix
            ey = by[src + v] - piy
            r2max = max(r2max, ex * ex + ey * ey)
        if nv < 3:
            break
    return src, nv, mult


@njit(cache=True, fastmath=False)
def _cell(pts, b, i, hw, key, idx, fv, bx, by):
    """Area and centroid ``(area, cx, cy)`` of cell ``i`` of env ``b``; the other arguments are scratch."""
    pix = pts[b, i, 0]
    piy = pts[b, i, 1]
    src, nv, mult = _clip_cell(pts, b, i, hw, key, idx, fv, bx, by)
    a2 = 0.0
    sx = 0.0
    sy = 0.0
    if nv >= 3:
        x0 = bx[src]
        y0 = by[src]
        for v in range(1, nv - 1):
            ux = bx[src + v] - x0
            uy = by[src + v] - y0
            wx = bx[src + v + 1] - x0
            wy = by[src + v + 1] - y0
            cr = ux * wy - uy * wx
            a2 += cr
            sx += cr * (ux + wx)
            sy += cr * (uy + wy)
    if a2 > 0.0:
        cx = bx[src] + sx / (3.0 * a2)
        cy = by[src] + sy / (3.0 * a2)
        area = 0.5 * a2 / mult
    else:
        cx = pix
        cy = piy
        area = 0.0
    cx = min(max(cx, -hw), hw)
    cy = min(max(cy, -hw), hw)
    return area, cx, cy


@njit(cache=True, fastmath=False)
def _scratch(n):
    """The scratch buffers of ``_clip_cell`` for ``n`` points per env: ``key, idx, fv, bx, by``."""
    # Exact arithmetic gives at most 4 + (N - 1) vertices; the slack absorbs rounding-made extra crossings.
    cap = 2 * n + 16
    return np.empty(n), np.empty(n, dtype=np.int64), np.empty(cap), np.empty(2 * cap), np.empty(2 * cap)


@njit(cache=True, fastmath=False)
def _run_cells(pts, hw, areas, cents, want_centroids, start, stop):
    """Cells ``start <= b * N + i < stop`` into ``areas`` (and ``cents`` when ``want_centroids``).

    Returns how many of those cells' own points are not finite (each point owns one cell, so the chunks
    together check every point). Non-finite input cannot overrun the buffers: every comparison with NaN is
    false, so no clip writes more than it would otherwise; the caller discards the output and raises.
    """
    n = pts.shape[1]
    key, idx, fv, bx, by = _scratch(n)
    bad = 0
    for cell in range(start, stop):
        b = cell // n
        i = cell - b * n
        if not (math.isfinite(pts[b, i, 0]) and math.isfinite(pts[b, i, 1])):
            bad += 1
        area, cx, cy = _cell(pts, b, i, hw, key, idx, fv, bx, by)
        areas[b, i] = area
        if want_centroids:
            cents[b, i, 0] = cx
            cents[b, i, 1] = cy
    return bad


@njit(parallel=True, cache=True, fastmath=False)
def _run_cells_parallel(pts, hw, areas, cents, want_centroids):
    total = pts.shape[0] * pts.shape[1]
    n_chunks = (total + _CHUNK - 1) // _CHUNK
    bad = 0
    for c in prange(n_chunks):
        bad += _run_cells(pts, hw, areas, cents, want_centroids, c * _CHUNK, min(total, (c + 1) * _CHUNK))
    return bad


def _as_points(points) -> np.ndarray:
    arr = np.asarray(points)
    if arr.dtype.kind not in "fiu":
        raise TypeError(f"points must be a real float array [B, N, 2], got dtype {arr.dtype}")
    if arr.ndim != 3 or arr.shape[2] != 2:
        raise ValueError(f"points must have shape [B, N, 2], got {arr.shape}")
    if arr.shape[1] < 1:
        raise ValueError(f"points needs at least one point per env (N >= 1), got shape {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.float64)


def _as_half_width(half_width) -> float:
    if type(half_width) is not float:  # the common case skips the slower abstract-type check
        if isinstance(half_width, (bool, np.bool_)) or not isinstance(half_width, numbers.Real):
            raise TypeError(f"half_width must be a real number, got {type(half_width).__name__}")
        half_width = float(half_width)
    if not math.isfinite(half_width):
        raise ValueError(f"half_width must be finite, got {half_width}")
    if half_width <= 0.0:
        raise ValueError(f"half_width must be > 0, got {half_width}")
    return half_width


def _compute(points, half_width, want_centroids: bool) -> tuple[np.ndarray, np.ndarray]:
    pts = _as_points(points)
    hw = _as_half_width(half_width)
    b, n = pts.shape[:2]
    areas = np.empty((b, n))
    cents = np.empty((b, n, 2) if want_centroids else (0, 0, 2))
    if b * n <= _SERIAL_CELLS:
        bad = _run_cells(pts, hw, areas, cents, want_centroids, 0, b * n)
    else:
        bad = _run_cells_parallel(pts, hw, areas, cents, want_centroids)
    if bad:
        raise ValueError(f"points contains NaN or inf ({bad} of {b * n} points): every coordinate must be finite")
    return areas, cents


def bounded_cells(points, half_width: float) -> tuple[np.ndarray, np.ndarray]:
    """Areas ``[B, N]`` and centroids ``[B, N, 2]`` of each point's Voronoi cell clipped to the square.

    ``points``: ``[B, N, 2]`` (float32 is converted), normally inside ``[-half_width, half_width]^2``;
    ``half_width`` in the same unit [m]. Conventions for coincident or outside points: module docstring.
    """
    return _compute(points, half_width, True)


def bounded_cell_areas(points, half_width: float) -> np.ndarray:
    """Areas ``[B, N]`` only, the reward's per-step call: same kernel as ``bounded_cells``."""
    return _compute(points, half_width, False)[0]


@njit(cache=True, fastmath=False)
def _polygons(pts, hw):
    n = pts.shape[1]
    key, idx, fv, bx, by = _scratch(n)
    cap = fv.shape[0]
    xs = np.empty((n, cap))
    ys = np.empty((n, cap))
    counts = np.zeros(n, dtype=np.int64)
    for i in range(n):
        src, nv, _ = _clip_cell(pts, 0, i, hw, key, idx, fv, bx, by)
        if nv >= 3:
            counts[i] = nv
            for v in range(nv):
                xs[i, v] = bx[src + v]
                ys[i, v] = by[src + v]
    return xs, ys, counts


def bounded_cell_polygons(points, half_width: float) -> list[np.ndarray]:
    """Each point's cell of one env, ``points [N, 2]``, as ``[V, 2]`` CCW vertices (``[0, 2]`` when empty): the
    very cells whose areas ``bounded_cells`` returns (for drawing). Coincident points each get the whole shared
    cell."""
    pts = _as_points(np.asarray(points)[None])
    hw = _as_half_width(half_width)
    if not np.isfinite(pts).all():
        raise ValueError("points contains NaN or inf: every coordinate must be finite")
    xs, ys, counts = _polygons(pts, hw)
    return [np.stack([xs[i, :k], ys[i, :k]], axis=1) for i, k in enumerate(counts)]
