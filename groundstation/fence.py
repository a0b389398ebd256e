"""The safety geofence's shape: its configuration, its geometry, and where a point lies relative to it.

Frame: the ground station's world frame, x and y horizontal, z up, metres (see ``mavlink_link`` for the
conversion to MAVLink's NED).

The fence is a convex polygon (or an axis-aligned box) in x, y with a minimum and maximum altitude, plus
circular keep-out zones (obstacles, as vertical cylinders). ``margin`` shrinks the polygon and the altitude
band and grows every keep-out circle; what is left is the *safe set*, the only place a setpoint may point
to. The band between the safe set and the fence itself absorbs tracking error, so a drone that is measured
beyond the fence itself has misbehaved and is stopped.

``check_position``, ``in_safe_set`` and ``clamp_position`` are pure functions of a ``FenceConfig`` and a
point; ``safety`` builds the velocity rule and the per-drone gate on them. Their arithmetic is compiled
(``fence_geometry``, numba): every setpoint passes it.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from groundstation import fence_geometry as fg
from groundstation.cf_firmware import WDT_SHUTDOWN_S
from runtime.geometry import clip_convex
from runtime.spec import SpecError, SwarmSpec, from_mapping, load_toml

TOL = fg.TOL
"""Slack [m] when testing membership of points computed exactly on a boundary."""
PARALLEL = fg.PARALLEL
"""Ray directions closer than this to parallel with a boundary plane are treated as parallel."""
FAR = 1e4
"""Inputs farther than this [m] beyond the fence's bounding box are pulled in before any arithmetic, so that
huge values cannot overflow."""


@dataclass(frozen=True)
class KeepOut:
    """A vertical cylinder no drone may enter (an obstacle)."""

    x: float
    """Centre x [m]."""
    y: float
    """Centre y [m]."""
    radius: float
    """Radius of the obstacle itself [m]; ``FenceConfig.margin`` is added around it."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.x) and math.isfinite(self.y)):
            raise SpecError(f"x: keep-out centre must be finite, got ({self.x!r}, {self.y!r})")
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise SpecError(f"radius: must be > 0 and finite, got {self.radius!r}")


def arena_box(spec: SwarmSpec | None = None) -> tuple[float, float, float, float]:
    """The square arena of ``spec`` (default: ``SwarmSpec()``) as a fence box ``(x_min, x_max, y_min, y_max)`` [m]."""
    hw = (spec if spec is not None else SwarmSpec()).arena.half_width
    return (-hw, hw, -hw, hw)


@dataclass(frozen=True)
class FenceConfig:
    """The geofence. Build it from TOML with ``FenceConfig.from_toml`` or from the arena with ``from_spec``."""

    box: tuple[float, ...] = field(default_factory=lambda: arena_box())
    """Horizontal box ``[x_min, x_max, y_min, y_max]`` [m]; used when ``vertices`` is empty. Default: the arena
    of the default spec (``arena_box``); ``from_toml(..., spec=...)`` gives a file without ``box`` and
    ``vertices`` the arena of that spec."""
    vertices: tuple[tuple[float, ...], ...] = ()
    """Corners ``[[x, y], ...]`` [m] of a convex horizontal polygon, in either winding order. When given it
    replaces ``box``."""
    z_min: float = 0.2
    """Lowest altitude of the fence [m, up]; setpoints stay at ``z_min + margin`` or above. A drone below
    ``z_min`` is on the ground, taking off or landing, which is not a violation."""
    z_max: float = 2.0
    """Highest altitude of the fence [m, up]; setpoints stay at ``z_max - margin`` or below."""
    margin: float = 0.2
    """Distance [m] between the fence and the safe set that setpoints are kept in: the polygon and the
    altitude band shrink by it, every keep-out circle grows by it. Covers tracking error and drone size."""
    keep_out: tuple[KeepOut, ...] = ()
    """Keep-out circles (obstacles), each ``{x, y, radius}`` [m]."""
    max_speed: float = 1.5
    """Largest speed [m/s] of any velocity setpoint."""
    max_decel: float = 2.0
    """Deceleration [m/s^2] the drone is sure to reach when braking; sets the stopping distance
    ``v^2 / (2 max_decel)`` that the velocity limit keeps free in front of the drone."""
    hold_time: float = 1.0
    """Time [s] a drone measured outside the fence hovers (holds) before it is landed."""
    coast_time: float = WDT_SHUTDOWN_S
    """Longest time [s] a drone may keep moving at its last commanded speed after the ground station falls
    silent; default the Crazyflie's setpoint-watchdog shutdown (0.5 s on the setpoint, then levelled and
    coasting, motors off at 2 s). Sets the second stopping distance ``|v| coast_time`` of the velocity limit."""

    def __post_init__(self) -> None:
        for name in ("z_min", "z_max", "margin", "max_speed", "max_decel", "hold_time", "coast_time"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise SpecError(f"fence.{name}: must be finite, got {v!r}")
        for name in ("max_speed", "max_decel", "coast_time"):
            if not getattr(self, name) > 0:
                raise SpecError(f"fence.{name}: must be > 0, got {getattr(self, name)!r}")
        for name in ("margin", "hold_time", "z_min"):
            if not getattr(self, name) >= 0:
                raise SpecError(f"fence.{name}: must be >= 0, got {getattr(self, name)!r}")
        if self.z_max - self.margin <= self.z_min + self.margin:
            raise SpecError(f"fence.z_max: the altitude band [{self.z_min}, {self.z_max}] m shrunk by margin "
                            f"{self.margin} m is empty: raise fence.z_max or lower fence.z_min or fence.margin")
        for i, k in enumerate(self.keep_out):
            if not isinstance(k, KeepOut):
                raise SpecError(f"fence.keep_out[{i}]: expected a KeepOut, got {type(k).__name__}")
        object.__setattr__(self, "_geom", Geometry.build(self))

    # -- construction ----------------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: dict, where: str = "fence") -> "FenceConfig":
        return from_mapping(cls, data, where)

    @classmethod
    def from_toml(cls, path: str | Path, table: str | None = "fence", spec: SwarmSpec | None = None) -> "FenceConfig":
        """The ``[table]`` of the TOML file; with ``spec``, a table without ``box`` and ``vertices`` fences
        that spec's arena."""
        data = load_toml(path)
        if table is not None:
            data = data.get(table, {})
        if spec is not None and isinstance(data, dict) and "box" not in data and "vertices" not in data:
            data = {**data, "box": list(arena_box(spec))}
        return cls.from_dict(data, where=table or "fence")

    @classmethod
    def from_spec(cls, spec: SwarmSpec, obstacles: np.ndarray | Sequence[Sequence[float]] | None = None,
                  **overrides: object) -> "FenceConfig":
        """The arena of ``spec`` as a box fence; ``obstacles`` rows ``(x, y, radius)`` [m] become keep-outs."""
        keep = tuple(KeepOut(float(o[0]), float(o[1]), float(o[2])) for o in (obstacles if obstacles is not None
                                                                            else ()))
        kwargs: dict = {"box": arena_box(spec), "keep_out": keep}
        kwargs.update(overrides)
        return cls(**kwargs)

    # -- derived ---------------------------------------------------------------------------------------
    @property
    def polygon(self) -> np.ndarray:
        """[n, 2] fence corners, counter-clockwise [m]."""
        return self._geom.outer.copy()  # type: ignore[attr-defined]

    @property
    def safe_polygon(self) -> np.ndarray:
        """[n, 2] corners of the polygon shrunk by the margin, counter-clockwise [m]."""
        return self._geom.inner.copy()  # type: ignore[attr-defined]

    @property
    def home(self) -> np.ndarray:
        """A point of the safe set near the fence's centre [m], the last-resort fallback setpoint."""
        return self._geom.home.copy()  # type: ignore[attr-defined]

    @property
    def z_band(self) -> tuple[float, float]:
        """Altitudes [m] that setpoints are kept between."""
        return self.z_min + self.margin, self.z_max - self.margin

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners [x, y, z] [m] of the box around the fence's flight volume."""
        poly = self._geom.outer  # type: ignore[attr-defined]
        return (np.array([*poly.min(axis=0), self.z_min]), np.array([*poly.max(axis=0), self.z_max]))


# --------------------------------------------------------------------------------------------------
# geometry


@dataclass(frozen=True)
class Geometry:
    """The fence precomputed for the per-setpoint checks (built once, by ``FenceConfig``)."""

    outer: np.ndarray          # [n, 2] ccw fence polygon
    normals: np.ndarray        # [n, 2] outward unit normals of its edges
    offsets: np.ndarray        # [n] fence: normals @ x <= offsets
    inner: np.ndarray          # [m, 2] ccw safe polygon
    inner_normals: np.ndarray
    inner_offsets: np.ndarray
    centres: np.ndarray        # [k, 2] keep-out centres
    radii: np.ndarray          # [k] keep-out radii (the obstacle itself)
    grown: np.ndarray          # [k] radii + margin
    z_lo: float
    z_hi: float
    lo: np.ndarray             # [2] bounding box of the fence, for pulling in huge inputs
    hi: np.ndarray
    home: np.ndarray           # [3]
    packed: np.ndarray         # all of the above but home as the one vector the compiled kernels take

    @staticmethod
    def build(f: FenceConfig) -> "Geometry":
        outer = _polygon_from_config(f)
        normals, offsets = _half_planes(outer)
        inner = outer.copy()
        for n, c in zip(normals, offsets - f.margin):
            inner = clip_convex(inner, n, c)
        if len(inner) < 3 or _area(inner) < 1e-6:
            raise SpecError(f"fence.margin: {f.margin} m leaves nothing of the fence polygon: lower fence.margin "
                            f"or enlarge the fence")
        inn, ino = _half_planes(inner)
        centres = np.array([[k.x, k.y] for k in f.keep_out], dtype=float).reshape(-1, 2)
        radii = np.array([k.radius for k in f.keep_out], dtype=float)
        z_lo, z_hi = f.z_band
        lo, hi = outer.min(axis=0) - FAR, outer.max(axis=0) + FAR
        packed = fg.pack(normals, offsets, inner, inn, ino, centres, radii, radii + f.margin, z_lo, z_hi,
                         f.z_min, f.z_max, lo, hi)
        g = Geometry(outer, normals, offsets, inner, inn, ino, centres, radii, radii + f.margin, z_lo, z_hi,
                     lo, hi, np.zeros(3), packed)
        xy = _clamp_xy(g, inner.mean(axis=0))
        if xy is None:
            raise SpecError("fence.keep_out: the keep-out circles (grown by the margin) cover the whole fence: "
                            "remove or shrink some, or lower fence.margin")
        object.__setattr__(g, "home", np.array([xy[0], xy[1], 0.5 * (z_lo + z_hi)]))
        return g


def geometry(fence: FenceConfig) -> Geometry:
    """The fence's precomputed geometry (polygons as half-planes, keep-out circles, the altitude band)."""
    return fence._geom  # type: ignore[attr-defined]


def _polygon_from_config(f: FenceConfig) -> np.ndarray:
    if f.vertices:
        for i, v in enumerate(f.vertices):
            if len(v) != 2 or not all(math.isfinite(c) for c in v):
                raise SpecError(f"fence.vertices[{i}]: expected [x, y] with finite numbers, got {list(v)!r}")
        poly = np.array(f.vertices, dtype=float)
        if len(poly) < 3:
            raise SpecError(f"fence.vertices: a polygon needs at least 3 corners, got {len(poly)}")
        area = _signed_area(poly)
        if abs(area) < 1e-6:
            raise SpecError("fence.vertices: the polygon has no area: check the corners")
        if area < 0:
            poly = poly[::-1].copy()
        e = np.roll(poly, -1, axis=0) - poly
        cross = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
        if np.any(cross < -1e-12) or np.any(np.hypot(e[:, 0], e[:, 1]) < 1e-9):
            raise SpecError("fence.vertices: the polygon must be convex without repeated corners: split a "
                            "concave area into keep-out circles or use a convex hull")
        return poly
    if len(f.box) != 4 or not all(math.isfinite(c) for c in f.box):
        raise SpecError(f"fence.box: expected [x_min, x_max, y_min, y_max] with finite numbers, got {list(f.box)!r}")
    x0, x1, y0, y1 = f.box
    if not (x0 < x1 and y0 < y1):
        raise SpecError(f"fence.box: need x_min < x_max and y_min < y_max, got {list(f.box)!r}")
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)


def _signed_area(p: np.ndarray) -> float:
    q = np.roll(p, -1, axis=0)
    return 0.5 * float(np.sum(p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]))


def _area(p: np.ndarray) -> float:
    return abs(_signed_area(p))


def _half_planes(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e = np.roll(poly, -1, axis=0) - poly
    n = np.stack([e[:, 1], -e[:, 0]], axis=1) / np.hypot(e[:, 0], e[:, 1])[:, None]
    return n, np.einsum("ij,ij->i", n, poly)


def _clamp_xy(g: Geometry, xy: np.ndarray) -> np.ndarray | None:
    """The nearest point of the horizontal safe set to finite ``xy`` [m], or None when the set is empty
    (``fence_geometry.clamp_xy``)."""
    out = np.empty(2)
    return out if fg.clamp_xy(g.packed, float(xy[0]), float(xy[1]), out) else None


def as_point(p: Sequence[float] | np.ndarray | None) -> np.ndarray | None:
    """``p`` as a finite float [3], or None when it is missing, malformed or not finite."""
    if p is None:
        return None
    try:
        a = np.asarray(p, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        return None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        return None
    return a


# --------------------------------------------------------------------------------------------------
# where a point is


class FenceStatus(enum.Enum):
    INSIDE = "inside"
    """In the safe set: where setpoints may point."""
    MARGIN = "margin"
    """Inside the fence but within its margin (tracking error)."""
    LOW = "low"
    """Below ``z_min`` over the allowed area: on the ground, taking off or landing."""
    OUTSIDE = "outside"
    """Beyond the fence, above ``z_max``, inside a keep-out circle, or at an unknown (non-finite) position."""


_STATUS = {fg.INSIDE: FenceStatus.INSIDE, fg.MARGIN: FenceStatus.MARGIN, fg.LOW: FenceStatus.LOW,
           fg.OUTSIDE: FenceStatus.OUTSIDE}


_F64 = np.dtype(np.float64)


def point3(p: object) -> np.ndarray | None:
    """``as_point``, without the copy for what is already a finite float64 [3] array (the setpoint path's: about
    0.5 us instead of 4)."""
    if type(p) is np.ndarray and p.dtype is _F64 and p.shape == (3,):
        x, y, z = p.tolist()
        if math.isfinite(x + y + z) or (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            return p  # (the sum of finite values can overflow; nan and inf reach it)
    return as_point(p)  # type: ignore[arg-type]


def check_position(fence: FenceConfig, p: Sequence[float] | np.ndarray | None) -> FenceStatus:
    """Where measured position ``p`` [m] is relative to the fence. Non-finite or missing counts as OUTSIDE."""
    a = point3(p)
    if a is None:
        return FenceStatus.OUTSIDE
    return _STATUS[fg.check(geometry(fence).packed, a)]


def in_safe_set(fence: FenceConfig, p: Sequence[float] | np.ndarray, tol: float = TOL) -> bool:
    """Whether ``p`` [m] lies in the safe set (within ``tol`` [m])."""
    a = point3(p)
    return a is not None and fg.in_safe_set(geometry(fence).packed, a, float(tol))


def clamp_position(fence: FenceConfig, p: Sequence[float] | np.ndarray | None,
                   fallback: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """The nearest point of the safe set to position setpoint ``p`` [m].

    A ``p`` that is missing or has any non-finite coordinate is replaced by ``fallback`` (pass the last safe
    setpoint or the drone's measured position), itself clamped; with no usable fallback the result is
    ``fence.home``. Coordinates absurdly far away are pulled in first so that nothing overflows."""
    a = point3(p)
    if a is None:
        a = point3(fallback)
        if a is None:
            return fence.home
    out = np.empty(3)
    if not fg.clamp_position(geometry(fence).packed, a, out):  # unreachable: the fence refuses configs
        return fence.home                                        # without a safe set
    return out


# --------------------------------------------------------------------------------------------------
# the fence against the arena the models were trained in


class FenceArenaMismatch(SpecError):
    """The fence does not contain the arena the models were trained in (to within its margin)."""


def arena_cut(fence: FenceConfig, spec: SwarmSpec) -> float:
    """How deep [m] the fence cuts into ``spec``'s arena: the largest distance by which a corner of the arena
    square lies beyond one of the fence's edges (0 when the fence contains the arena)."""
    g = geometry(fence)
    x0, x1, y0, y1 = arena_box(spec)
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    return max(0.0, float((corners @ g.normals.T - g.offsets[None]).max()))


def check_arena(fence: FenceConfig, spec: SwarmSpec, fence_name: str = "the fence",
                models_name: str = "the models") -> None:
    """Raise ``FenceArenaMismatch`` naming both when ``fence`` cuts the arena that ``spec`` (the models' spec)
    trained in by more than its margin: the policies would steer at walls the geofence holds them off, or the
    fence would be drawn for another area. A fence may be smaller by up to its margin (the default fence is
    the arena itself: its safe set is the arena shrunk by the margin)."""
    cut = arena_cut(fence, spec)
    if cut <= fence.margin + TOL:
        return
    hw = spec.arena.half_width
    shape = (f"box {[round(v, 3) for v in fence.box]}" if not fence.vertices
             else f"polygon {[[round(c, 3) for c in v] for v in fence.vertices]}")
    raise FenceArenaMismatch(
        f"{fence_name}: the fence ({shape} m, margin {fence.margin} m) cuts {cut:.2f} m into the arena "
        f"{models_name} were trained in ([{-hw}, {hw}]^2 m, spec {spec.hash}), more than its margin: make the "
        f"fence cover that arena to within {fence.margin} m, or fly models trained for this fence's area")
