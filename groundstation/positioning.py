"""Where every drone is: per-drone state from the links' telemetry, staleness, and the LPS anchor layout.

``PositionTracker`` keeps the latest ``DroneState`` of each drone, fed by a link's telemetry (any object with
``t``, ``position``, ``velocity``, ``battery``, ``link_quality`` and ``flight_state``, such as
``groundstation.link.Telemetry``). A state older than ``stale_after`` (default 0.2 s, two control periods) is
stale: callers must not steer a drone by it (the geofence treats a missing position as outside the fence).

``AnchorLayout`` is the Loco Positioning System's anchors (the paper: 8 UWB anchors, two on each of 4 stands
at the corners of the 6 m x 6 m area), loaded from TOML and checked against the fence: UWB positioning is
only trustworthy inside the box the anchors span.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from groundstation.cf_firmware import LIPO_CHARGE_CURVE_V, lipo_state_of_charge
from runtime.spec import SpecError, SwarmSpec, from_mapping, load_toml

if TYPE_CHECKING:  # only for annotations: positioning works with any link that publishes telemetry
    from matplotlib.axes import Axes

    from groundstation.link import Link
    from groundstation.safety import FenceConfig

log = logging.getLogger(__name__)

BATTERY_EMPTY_V = LIPO_CHARGE_CURVE_V[0]
"""Voltage [V] of an empty 1S LiPo (Crazyflie)."""
BATTERY_FULL_V = LIPO_CHARGE_CURVE_V[-1]
"""Voltage [V] of a full 1S LiPo."""


def battery_fraction(voltage: float) -> float:
    """State of charge [0..1] from a battery voltage [V] by the LiPo charge curve of the Crazyflie firmware
    (``cf_firmware.LIPO_CHARGE_CURVE_V``), not a straight line: a LiPo spends most of its charge between
    3.8 and 4.1 V and drops through its knee below 10 %. Non-finite voltages read as empty. A voltage under
    load reads lower than at rest; compare drones in the same state (all flying, or all on the ground)."""
    return lipo_state_of_charge(voltage)


@dataclass(frozen=True)
class DroneState:
    """One drone as the ground station last heard from it."""

    drone_id: str
    position: tuple[float, float, float]
    """[m, world frame, z up]"""
    velocity: tuple[float, float, float]
    """[m/s, world frame]"""
    battery: float
    """Battery voltage [V]."""
    link_quality: float
    """[0..1]"""
    flight_state: Any
    """The link's ``FlightState`` (or whatever the telemetry carried)."""
    t: float
    """When the telemetry arrived [s, the tracker's monotonic clock]."""

    @property
    def battery_fraction(self) -> float:
        """State of charge [0..1] from the voltage (``battery_fraction``)."""
        return battery_fraction(self.battery)

    def age(self, now: float) -> float:
        return now - self.t


def _vec3(value: Any, name: str) -> tuple[float, float, float]:
    a = np.asarray(value, dtype=float).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"telemetry.{name}: expected 3 numbers, got {value!r}")
    return float(a[0]), float(a[1]), float(a[2])


class PositionTracker:
    """Latest state per drone, thread-safe (links publish from their receive threads).

    >>> tracker = PositionTracker(stale_after=0.2)
    >>> tracker.attach("cf1", link)          # or tracker.update("cf1", link.telemetry())
    >>> tracker.fresh("cf1")                 # None when unknown or older than 0.2 s
    """

    def __init__(self, stale_after: float = 0.2, clock: Callable[[], float] = time.monotonic) -> None:
        if not (math.isfinite(stale_after) and stale_after > 0):
            raise ValueError(f"stale_after must be > 0 s, got {stale_after!r}")
        self.stale_after = stale_after
        self.clock = clock
        self._states: dict[str, DroneState] = {}
        self._was_stale: dict[str, bool] = {}
        self._callbacks: dict[str, tuple[Any, Callable[[Any], None]]] = {}
        self._lock = threading.Lock()

    # -- feeding -------------------------------------------------------------------------------------
    def update(self, drone_id: str, telemetry: Any) -> DroneState | None:
        """Take one telemetry sample. Its ``t`` (arrival time, same monotonic clock) stamps the state; a
        sample without a finite ``t`` is stamped now. Samples older than the held one are ignored.
        Malformed samples are logged and dropped. Returns the held state."""
        if telemetry is None:
            return self.get(drone_id)
        try:
            t = getattr(telemetry, "t", None)
            t = float(t) if t is not None and math.isfinite(float(t)) else self.clock()
            state = DroneState(drone_id, _vec3(telemetry.position, "position"),
                               _vec3(telemetry.velocity, "velocity"), float(telemetry.battery),
                               float(telemetry.link_quality), telemetry.flight_state, t)
        except (AttributeError, TypeError, ValueError) as exc:
            log.warning("positioning: dropped a malformed telemetry sample of %s: %s", drone_id, exc)
            return self.get(drone_id)
        with self._lock:
            held = self._states.get(drone_id)
            if held is not None and state.t < held.t:
                return held
            self._states[drone_id] = state
            if self._was_stale.get(drone_id):
                log.info("positioning: %s fresh again", drone_id)
            self._was_stale[drone_id] = False
        return state

    def attach(self, drone_id: str, link: "Link") -> None:
        """Follow ``link``'s telemetry as ``drone_id`` (registers a telemetry callback)."""
        def feed(sample: Any) -> None:
            self.update(drone_id, sample)
        self.detach(drone_id)
        link.add_telemetry_callback(feed)
        self._callbacks[drone_id] = (link, feed)
        self.update(drone_id, link.telemetry())

    def detach(self, drone_id: str) -> None:
        held = self._callbacks.pop(drone_id, None)
        if held is not None:
            link, feed = held
            try:
                link.remove_telemetry_callback(feed)
            except ValueError:
                log.debug("positioning: callback of %s was already removed", drone_id)

    def forget(self, drone_id: str) -> None:
        """Drop a drone (disconnected for good)."""
        self.detach(drone_id)
        with self._lock:
            self._states.pop(drone_id, None)
            self._was_stale.pop(drone_id, None)

    # -- reading -------------------------------------------------------------------------------------
    @property
    def drone_ids(self) -> list[str]:
        with self._lock:
            return sorted(self._states)

    def get(self, drone_id: str) -> DroneState | None:
        """The latest state, stale or not; None if never heard of."""
        with self._lock:
            return self._states.get(drone_id)

    def age(self, drone_id: str) -> float:
        """Seconds since the latest sample [s]; inf if none."""
        s = self.get(drone_id)
        return math.inf if s is None else s.age(self.clock())

    def is_stale(self, drone_id: str) -> bool:
        stale = self.age(drone_id) > self.stale_after
        with self._lock:
            if stale and drone_id in self._states and not self._was_stale.get(drone_id):
                self._was_stale[drone_id] = True
                log.warning("positioning: %s stale (no telemetry for %.2f s)", drone_id,
                            self._states[drone_id].age(self.clock()))
        return stale

    def fresh(self, drone_id: str) -> DroneState | None:
        """The latest state if it is not stale, else None."""
        s = self.get(drone_id)
        return None if s is None or self.is_stale(drone_id) else s

    def position(self, drone_id: str) -> np.ndarray | None:
        """Fresh position [m] or None: what the geofence should be given as the measured position."""
        s = self.fresh(drone_id)
        return None if s is None else np.array(s.position)

    def snapshot(self) -> dict[str, DroneState]:
        with self._lock:
            return dict(self._states)

    def stale_ids(self) -> list[str]:
        return [d for d in self.drone_ids if self.is_stale(d)]


# --------------------------------------------------------------------------------------------------
# LPS anchors


@dataclass(frozen=True)
class Anchor:
    """One UWB anchor."""

    id: int
    """Anchor id as configured in the node (0..7 for a standard LPS)."""
    position: tuple[float, ...]
    """[x, y, z] [m, world frame, z up]."""
    stand: str
    """Which stand holds it (for the setup checklist); required, like every anchor key, because the strict
    loader has no default anchor to take missing keys from."""

    def __post_init__(self) -> None:
        if len(self.position) != 3 or not all(math.isfinite(c) for c in self.position):
            raise SpecError(f"position: expected [x, y, z] with finite numbers, got {list(self.position)!r}")
        if not 0 <= self.id <= 255:
            raise SpecError(f"id: must be in 0..255, got {self.id}")


def paper_anchors(half_width: float | None = None, low: float = 0.15, high: float = 2.3) -> tuple[Anchor, ...]:
    """The paper's layout: a stand on each corner of the square ``[-half_width, half_width]^2`` [m] (None: the
    default spec's arena), one anchor ``low`` and one ``high`` [m] on each (the heights are not in the paper;
    these are examples)."""
    if half_width is None:
        half_width = SwarmSpec().arena.half_width
    corners = (("south-west", -1, -1), ("south-east", 1, -1), ("north-east", 1, 1), ("north-west", -1, 1))
    return tuple(Anchor(2 * k + j, (sx * half_width, sy * half_width, z), name)
                 for k, (name, sx, sy) in enumerate(corners) for j, z in enumerate((low, high)))


@dataclass(frozen=True)
class AnchorLayout:
    """The LPS anchors. Load with ``AnchorLayout.from_toml``; check against the fence with ``check_covers``."""

    anchors: tuple[Anchor, ...] = field(default_factory=paper_anchors)
    """The anchors (at least 4; the paper used 8). Defaults to ``paper_anchors()``."""
    expected_count: int = 8
    """How many anchors this installation must have [-]; a different count is an error (a missing anchor in
    the file usually means a missing anchor on the stand)."""
    tolerance: float = 0.1
    """How far [m] the fence's flight volume may stick out of the box the anchors span."""

    def __post_init__(self) -> None:
        n = len(self.anchors)
        if n < 4:
            raise SpecError(f"lps.anchors: {n} anchors cannot give a 3-D position; at least 4 are needed "
                            f"(the paper's setup has 8)")
        if self.expected_count < 4:
            raise SpecError(f"lps.expected_count: must be >= 4, got {self.expected_count}")
        if n != self.expected_count:
            raise SpecError(f"lps.anchors: {n} anchors listed but lps.expected_count is {self.expected_count}: "
                            f"add the missing anchors or set lps.expected_count = {n}")
        ids = [a.id for a in self.anchors]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise SpecError(f"lps.anchors: anchor ids {dup} appear more than once: give every anchor its own id")
        if not (math.isfinite(self.tolerance) and self.tolerance >= 0):
            raise SpecError(f"lps.tolerance: must be >= 0, got {self.tolerance!r}")
        p = self.positions
        sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
        if sv[-1] < 1e-3 * max(sv[0], 1e-9):
            raise SpecError("lps.anchors: all anchors lie in one plane, so height cannot be resolved: mount "
                            "some anchors high and some low")

    @property
    def positions(self) -> np.ndarray:
        """[n, 3] anchor positions [m]."""
        return np.array([a.position for a in self.anchors], dtype=float)

    def span(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners of the box the anchors span [m]."""
        p = self.positions
        return p.min(axis=0), p.max(axis=0)

    def check_covers(self, fence: "FenceConfig") -> None:
        """Raise ``SpecError`` naming the axis when the fence's flight volume leaves the anchors' box by more
        than ``tolerance``."""
        lo, hi = self.span()
        flo, fhi = fence.bounds()
        for k, axis in enumerate("xyz"):
            if flo[k] < lo[k] - self.tolerance or fhi[k] > hi[k] + self.tolerance:
                raise SpecError(
                    f"lps.anchors: the anchors span {axis} in [{lo[k]:.2f}, {hi[k]:.2f}] m but the fence's flight "
                    f"volume needs [{flo[k]:.2f}, {fhi[k]:.2f}] m (tolerance {self.tolerance} m): move the "
                    f"anchors outward or shrink the fence")

    @classmethod
    def from_dict(cls, data: dict, where: str = "lps") -> "AnchorLayout":
        return from_mapping(cls, data, where)

    @classmethod
    def from_toml(cls, path: str | Path, table: str = "lps", fence: "FenceConfig | None" = None) -> "AnchorLayout":
        """Load and validate; with ``fence`` also check that the anchors cover it."""
        layout = cls.from_dict(load_toml(path).get(table, {}), where=table)
        if fence is not None:
            layout.check_covers(fence)
        return layout


def draw_layout(ax: "Axes", fence: "FenceConfig | None" = None, anchors: AnchorLayout | None = None) -> None:
    """Draw the fence (solid), its safe set (dashed), the keep-out circles and the anchors (triangles with
    their ids) on a top-down matplotlib ``ax`` [m]."""
    from matplotlib.patches import Circle, Polygon

    if fence is not None:
        ax.add_patch(Polygon(fence.polygon, closed=True, fill=False, edgecolor="tab:red", linewidth=1.5,
                             label="fence"))
        ax.add_patch(Polygon(fence.safe_polygon, closed=True, fill=False, edgecolor="tab:red", linestyle="--",
                             linewidth=1.0, label="setpoint limit"))
        for k in fence.keep_out:
            ax.add_patch(Circle((k.x, k.y), k.radius, color="tab:gray", alpha=0.6))
            ax.add_patch(Circle((k.x, k.y), k.radius + fence.margin, fill=False, edgecolor="tab:gray",
                                linestyle="--"))
    if anchors is not None:
        p = anchors.positions
        ax.scatter(p[:, 0], p[:, 1], marker="^", color="tab:blue", zorder=5, label="LPS anchors")
        for a in anchors.anchors:  # anchors on one stand share x, y: stack their labels
            same = [b.id for b in anchors.anchors if b.position[:2] == a.position[:2]]
            if a.id == min(same):
                ax.annotate(",".join(str(i) for i in sorted(same)), a.position[:2], textcoords="offset points",
                            xytext=(4, 4), fontsize=7, color="tab:blue")
    ax.set_aspect("equal")
    ax.autoscale_view()
