"""Per-drone state from telemetry, staleness, and the LPS anchor layout."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from groundstation.link import FlightState, Telemetry
from groundstation.positioning import AnchorLayout, DroneState, PositionTracker, draw_layout
from groundstation.safety import FenceConfig
from runtime.spec import SpecError

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Sample:  # the fields of groundstation.link.Telemetry that positioning reads
    t: float
    position: tuple
    velocity: tuple = (0.0, 0.0, 0.0)
    battery: float = 3.9
    link_quality: float = 1.0
    flight_state: str = "flying"


class Clock:
    def __init__(self) -> None:
        self.t = 50.0

    def __call__(self) -> float:
        return self.t


class FakeLink:
    """Just the publishing side of ``Link``: callbacks and the latest sample."""

    def __init__(self) -> None:
        self.callbacks: list[Callable[[Any], None]] = []
        self.latest: Sample | None = None

    def add_telemetry_callback(self, cb: Callable[[Any], None]) -> None:
        self.callbacks.append(cb)

    def remove_telemetry_callback(self, cb: Callable[[Any], None]) -> None:
        self.callbacks.remove(cb)

    def telemetry(self) -> Sample | None:
        return self.latest

    def publish(self, s: Sample) -> None:
        self.latest = s
        for cb in list(self.callbacks):
            cb(s)


def test_state_goes_stale_after_the_configured_time(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    tr = PositionTracker(clock=clock)
    assert tr.stale_after == 0.2
    assert tr.fresh("cf1") is None and tr.age("cf1") == float("inf")
    s = tr.update("cf1", Sample(t=50.0, position=(1.0, 2.0, 0.5), velocity=[0.1, 0.0, 0.0]))
    assert isinstance(s, DroneState) and s.position == (1.0, 2.0, 0.5) and s.velocity == (0.1, 0.0, 0.0)
    clock.t = 50.19
    np.testing.assert_allclose(tr.position("cf1"), (1.0, 2.0, 0.5))
    clock.t = 50.21
    with caplog.at_level(logging.WARNING, logger="groundstation.positioning"):
        assert tr.is_stale("cf1") and tr.fresh("cf1") is None and tr.position("cf1") is None
        assert tr.is_stale("cf1")
    assert sum("stale" in r.getMessage() for r in caplog.records) == 1  # logged once per outage
    assert tr.get("cf1") is s and tr.stale_ids() == ["cf1"]
    tr.update("cf1", Sample(t=50.21, position=(1.0, 2.0, 0.6)))
    assert tr.fresh("cf1").position[2] == 0.6 and tr.stale_ids() == []


def test_old_and_malformed_samples_are_dropped_and_custom_staleness() -> None:
    clock = Clock()
    tr = PositionTracker(stale_after=1.0, clock=clock)
    tr.update("a", Sample(t=50.0, position=(0, 0, 1)))
    tr.update("a", Sample(t=49.0, position=(9, 9, 9)))  # out of order
    assert tr.get("a").position == (0, 0, 1)
    tr.update("a", Sample(t=50.1, position=(1, 2)))     # malformed
    tr.update("a", object())
    assert tr.get("a").position == (0, 0, 1)
    tr.update("b", Sample(t=float("nan"), position=(0, 0, 0)))  # no usable stamp: stamped now
    assert tr.get("b").t == 50.0
    clock.t = 50.9
    assert tr.fresh("a") is not None
    with pytest.raises(ValueError):
        PositionTracker(stale_after=0)


def test_attach_follows_a_links_telemetry_and_battery_fraction() -> None:
    clock = Clock()
    tr = PositionTracker(clock=clock)
    link = FakeLink()
    link.latest = Sample(t=50.0, position=(0.0, 0.0, 0.0), battery=4.2)
    tr.attach("cf2", link)
    assert tr.get("cf2").battery_fraction == 1.0
    link.publish(Sample(t=50.05, position=(0.5, 0.0, 1.0), battery=3.92))
    assert tr.get("cf2").position == (0.5, 0.0, 1.0)
    assert tr.get("cf2").battery_fraction == pytest.approx(0.5)  # the LiPo curve's 50 % point
    tr.forget("cf2")
    assert link.callbacks == [] and tr.get("cf2") is None


def test_tracker_with_the_real_telemetry_type() -> None:
    tr = PositionTracker()
    sample = Telemetry(t=1.0, position=(1.0, 0.0, 0.3), velocity=(0.0, 0.0, 0.0), battery=3.7,
                       link_quality=0.9, flight_state=FlightState.FLYING)
    s = tr.update("x", sample)
    assert s.flight_state is FlightState.FLYING and s.link_quality == 0.9


# -- anchors -------------------------------------------------------------------------------------------


def test_shipped_layout_is_the_papers_and_covers_the_fence() -> None:
    fence = FenceConfig.from_toml(ROOT / "configs" / "fence.toml")
    layout = AnchorLayout.from_toml(ROOT / "configs" / "lps_anchors.toml", fence=fence)
    assert len(layout.anchors) == 8
    stands = {a.position[:2] for a in layout.anchors}
    assert stands == {(-3.0, -3.0), (3.0, -3.0), (3.0, 3.0), (-3.0, 3.0)}
    assert all(sum(a.position[:2] == s for a in layout.anchors) == 2 for s in stands)


def _anchors(n: int, z: tuple[float, float] = (0.15, 2.3), hw: float = 3.0) -> list[dict]:
    corners = [(-hw, -hw), (hw, -hw), (hw, hw), (-hw, hw)]
    return [{"id": i, "stand": f"s{i // 2}", "position": [*corners[(i // 2) % 4], z[i % 2]]} for i in range(n)]


@pytest.mark.parametrize("data, field", [
    ({"anchors": _anchors(4), "expected_count": 3}, "lps.expected_count"),
    ({"anchors": _anchors(3)}, "lps.anchors"),
    ({"anchors": _anchors(6)}, "lps.anchors"),
    ({"anchors": _anchors(8, z=(1.0, 1.0))}, "lps.anchors"),
    ({"anchors": [dict(a, id=0) for a in _anchors(8)]}, "lps.anchors"),
    ({"anchors": [{"id": 0, "stand": "s0", "position": [0.0, 1.0]}] + _anchors(8)[1:]}, "lps.anchors[0].position"),
    ({"anchors": _anchors(8), "tolerance": -1.0}, "lps.tolerance"),
    ({"anchors": _anchors(8), "anchor_count": 8}, "lps.anchor_count"),
])
def test_bad_layouts_name_the_field(data: dict, field: str) -> None:
    with pytest.raises(SpecError) as err:
        AnchorLayout.from_dict(data)
    assert str(err.value).startswith(field), str(err.value)


def test_anchors_must_span_the_flight_volume() -> None:
    fence = FenceConfig()
    AnchorLayout.from_dict({"anchors": _anchors(6), "expected_count": 6}).check_covers(fence)
    small = AnchorLayout.from_dict({"anchors": _anchors(8, hw=2.5)})
    with pytest.raises(SpecError, match=r"lps.anchors: the anchors span x in \[-2.50, 2.50\]"):
        small.check_covers(fence)
    low = AnchorLayout.from_dict({"anchors": _anchors(8, z=(0.15, 1.5))})
    with pytest.raises(SpecError, match="span z"):
        low.check_covers(fence)
    AnchorLayout.from_dict({"anchors": _anchors(8, hw=2.95)}).check_covers(fence)  # within tolerance


def test_draw_layout_puts_fence_keepouts_and_anchors_on_the_axes(tmp_path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fence = FenceConfig.from_toml(ROOT / "configs" / "fence.toml")
    layout = AnchorLayout.from_toml(ROOT / "configs" / "lps_anchors.toml")
    fig, ax = plt.subplots()
    draw_layout(ax, fence, layout)
    assert len(ax.patches) == 2 + 2 * len(fence.keep_out)
    assert len(ax.collections) == 1 and len(ax.collections[0].get_offsets()) == 8
    assert sorted(t.get_text() for t in ax.texts) == ["0,1", "2,3", "4,5", "6,7"]
    fig.savefig(tmp_path / "layout.png")
    plt.close(fig)
    assert (tmp_path / "layout.png").stat().st_size > 1000


def test_battery_fraction_follows_the_lipo_curve_with_its_knee() -> None:
    from groundstation.cf_firmware import LIPO_CHARGE_CURVE_V, lipo_resting_voltage
    from groundstation.positioning import battery_fraction

    assert battery_fraction(4.2) == 1.0 and battery_fraction(3.0) == 0.0 and battery_fraction(float("nan")) == 0.0
    assert battery_fraction(2.5) == 0.0 and battery_fraction(4.4) == 1.0
    for k, v in enumerate(LIPO_CHARGE_CURVE_V):  # the inverse of the simulator's discharge curve
        assert battery_fraction(v) == pytest.approx(k / 10)
        assert lipo_resting_voltage(k / 10) == pytest.approx(v)
    # the knee: the last 10 % of the charge spans more voltage than the 80 % above it
    assert LIPO_CHARGE_CURVE_V[1] - LIPO_CHARGE_CURVE_V[0] > LIPO_CHARGE_CURVE_V[9] - LIPO_CHARGE_CURVE_V[1]
    assert battery_fraction(3.6) < 0.1  # linear in 3.0-4.2 V it would read 0.5
