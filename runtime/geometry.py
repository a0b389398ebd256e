"""Clipping a convex polygon by a half-plane (Sutherland-Hodgman): the one implementation.

``training.voronoi`` builds every bounded Voronoi cell of the scouts' reward with it (proven against shapely and
scipy in ``tests/test_voronoi.py``), ``training.plots`` draws those same cells, and ``groundstation.fence``
shrinks the geofence's polygon by its margin with it.

``clip_into`` works on vertex buffers (numba, no allocation: the Voronoi kernel calls it millions of times a
second); ``clip_convex`` is the same clip for one ``[n, 2]`` array. numba caches a caller's machine code by the
caller's own file: after editing ``clip_into``, touch ``training/voronoi.py`` (or clear its ``__pycache__``)
so that its cached kernels are rebuilt.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["clip_convex", "clip_into"]


@njit(cache=True, nogil=True, inline="always")
def clip_into(xs, ys, src, nv, fv, dst, cap):
    """The part of the polygon ``xs[src:src + nv], ys[src:src + nv]`` (convex, either winding) on the inner side
    of a line, written to ``xs[dst:], ys[dst:]`` (at most ``cap`` vertices, same winding); returns how many.

    ``fv[:nv]`` are the vertices' signed distances to the line, ``> 0`` outside (any positive multiple of the
    distance will do). A vertex with ``fv <= 0`` is kept; a crossing adds ``a + t (b - a)``, ``t = fa / (fa -
    fb)``. Strict signs for crossings: a vertex lying on the line is kept once, never doubled by a zero-length
    cut. Source and destination ranges must not overlap."""
    out = 0
    for v in range(nv):
        w = v + 1 if v + 1 < nv else 0
        fa = fv[v]
        fb = fv[w]
        ax = xs[src + v]
        ay = ys[src + v]
        if fa <= 0.0 and out < cap:
            xs[dst + out] = ax
            ys[dst + out] = ay
            out += 1
        if ((fa < 0.0 and fb > 0.0) or (fa > 0.0 and fb < 0.0)) and out < cap:
            t = fa / (fa - fb)
            xs[dst + out] = ax + t * (xs[src + w] - ax)
            ys[dst + out] = ay + t * (ys[src + w] - ay)
            out += 1
    return out


@njit(cache=True, nogil=True)
def _clip_array(px, py, nx, ny, c):
    n = px.shape[0]
    cap = 2 * n + 2  # a convex polygon gains at most one vertex per clip; the slack absorbs rounding
    xs = np.empty(n + cap)
    ys = np.empty(n + cap)
    fv = np.empty(n)
    for v in range(n):
        xs[v] = px[v]
        ys[v] = py[v]
        fv[v] = nx * px[v] + ny * py[v] - c
    m = clip_into(xs, ys, 0, n, fv, n, cap)
    return xs[n:n + m].copy(), ys[n:n + m].copy()


def clip_convex(poly: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """The part of convex polygon ``poly [n, 2]`` where ``normal . x <= offset``, as ``[m, 2]`` (m may be 0)."""
    p = np.asarray(poly, dtype=np.float64).reshape(-1, 2)
    if len(p) == 0:
        return np.zeros((0, 2))
    x, y = _clip_array(np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]), float(normal[0]),
                       float(normal[1]), float(offset))
    return np.stack([x, y], axis=1)
