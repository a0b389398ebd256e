"""The fence against the arena the models were trained in: the numbers come from the spec, and a fence that cuts
the arena by more than its margin is refused, naming both, before anything takes off."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from groundstation.demo import DemoError, DemoOptions, run_demo
from groundstation.fence import FenceArenaMismatch, FenceConfig, arena_box, arena_cut, check_arena
from groundstation.fleet import FleetConfig, fly
from groundstation.flight import FlightConfig
from groundstation.positioning import paper_anchors
from groundstation.roles import arena_side
from runtime.policy import read_manifest
from runtime.spec import SwarmSpec

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models" / "role_based"


def _spec(half_width: float) -> SwarmSpec:
    s = SwarmSpec()
    return dataclasses.replace(s, arena=dataclasses.replace(s.arena, half_width=half_width))


def test_the_ground_station_s_arena_numbers_are_the_spec_s():
    hw = SwarmSpec().arena.half_width
    assert FenceConfig().box == arena_box() == (-hw, hw, -hw, hw)
    assert max(abs(c) for a in paper_anchors() for c in a.position[:2]) == hw
    assert arena_side() == 2 * hw
    big = _spec(4.0)
    assert FenceConfig.from_spec(big).box == (-4.0, 4.0, -4.0, 4.0)


def test_a_fence_file_without_box_or_vertices_fences_the_models_arena(tmp_path):
    (tmp_path / "f.toml").write_text("[fence]\nmargin = 0.3\n")
    assert FenceConfig.from_toml(tmp_path / "f.toml", spec=_spec(4.0)).box == (-4.0, 4.0, -4.0, 4.0)
    assert FenceConfig.from_toml(tmp_path / "f.toml").box == arena_box()
    (tmp_path / "g.toml").write_text("[fence]\nbox = [-1.0, 1.0, -2.0, 2.0]\n")
    assert FenceConfig.from_toml(tmp_path / "g.toml", spec=_spec(4.0)).box == (-1.0, 1.0, -2.0, 2.0)
    fence = FenceConfig.from_toml(ROOT / "configs" / "fence.toml", spec=read_manifest(MODELS).spec)
    check_arena(fence, read_manifest(MODELS).spec)  # the shipped fence fits the shipped models


@pytest.mark.parametrize("fence, cut", [
    (FenceConfig(), 0.0),
    (FenceConfig(box=(-4.0, 4.0, -4.0, 4.0)), 0.0),                 # bigger: contains the arena
    (FenceConfig(box=(-2.85, 3.0, -3.0, 3.0)), 0.15),               # smaller by less than its margin
    (FenceConfig(box=(-3.0, 3.0, -3.0, 2.8)), 0.2),                 # by exactly its margin
    (FenceConfig(vertices=((-3.0, -3.0), (3.0, -3.0), (3.0, 2.9), (2.9, 3.0), (-3.0, 3.0))), 0.0707),  # a corner
])
def test_fences_within_their_margin_of_the_arena_pass(fence, cut):
    spec = SwarmSpec()
    assert arena_cut(fence, spec) == pytest.approx(cut, abs=1e-4)
    check_arena(fence, spec)


@pytest.mark.parametrize("fence, spec, words", [
    (FenceConfig(box=(-2.5, 2.5, -2.5, 2.5)), SwarmSpec(), ["cuts 0.50 m", "box [-2.5, 2.5, -2.5, 2.5]"]),
    (FenceConfig(box=(-3.0, 3.0, -3.0, 2.79)), SwarmSpec(), ["cuts 0.21 m"]),
    (FenceConfig(box=(-3.0, 3.0, -3.0, 3.0), margin=0.05), _spec(3.5), ["cuts 0.50 m", "[-3.5, 3.5]^2"]),
    (FenceConfig(vertices=((0.0, -3.0), (3.0, 0.0), (0.0, 3.0), (-3.0, 0.0))), SwarmSpec(), ["polygon"]),
])
def test_a_fence_that_cuts_the_arena_by_more_than_its_margin_names_both(fence, spec, words):
    with pytest.raises(FenceArenaMismatch) as err:
        check_arena(fence, spec, "fence configs/x.toml", "the models in models/y")
    msg = str(err.value)
    assert "\n" not in msg
    for w in ["fence configs/x.toml", "the models in models/y", spec.hash, f"margin {fence.margin}", *words]:
        assert w in msg, (w, msg)


def test_demo_and_fly_refuse_such_a_fence_before_anything_starts(tmp_path, monkeypatch):
    small = tmp_path / "small.toml"
    small.write_text("[fence]\nbox = [-2.0, 2.0, -3.0, 3.0]\n")
    started = []
    monkeypatch.setattr("groundstation.demo.SimProcess", lambda *a, **k: started.append(a))
    monkeypatch.setattr("groundstation.demo.SimSwarm", lambda *a, **k: started.append(a))
    with pytest.raises(DemoError, match=r"cuts 1\.00 m into the arena the models in .*role_based"):
        run_demo(DemoOptions(models=str(MODELS), fence=str(small), anchors=str(ROOT / "configs" / "lps_anchors.toml")))
    assert not started
    monkeypatch.setattr("groundstation.fleet.open_fleet", lambda *a, **k: started.append(a))
    fleet = dataclasses.replace(FleetConfig(), models=str(MODELS), fence=str(small))
    with pytest.raises(FenceArenaMismatch, match="cuts 1.00 m"):
        fly(fleet, FlightConfig(), 1.0)
    assert not started
