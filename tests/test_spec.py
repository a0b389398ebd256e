import math

import pytest

from runtime.spec import Role, SpecError, SwarmSpec, load_toml
from training.config import ExperimentConfig


def test_defaults_match_the_paper():
    s = SwarmSpec()
    assert s.arena.half_width == 3.0 and s.arena.n_obstacles == 3
    assert s.pursuer.radius == 0.075 and s.scout.radius == 0.075 and s.evader.radius == 0.05
    assert s.evader.max_speed == pytest.approx(1.3 * s.pursuer.max_speed)
    assert s.sensing.sensing_range == 0.5
    assert s.roles == (Role.PURSUER,) * 5 + (Role.SCOUT,) * 5 + (Role.EVADER,) * 2


def test_layout_slices_are_contiguous_and_named():
    s = SwarmSpec()
    for role in Role:
        lay = s.layout(role)
        pos = 0
        for f in lay.fields:
            assert f.slice.start == pos
            assert len(f.units) == len(f.columns) == len(f.low) == len(f.high)
            pos += f.size
        assert pos == lay.dim == s.obs_dim(role)
        lo, hi = lay.bounds()
        assert len(lo) == len(hi) == lay.dim and all(a <= b for a, b in zip(lo, hi))
    assert s.layout(Role.PURSUER)["targets"].rows == s.team.n_evaders
    assert "threats" in s.layout(Role.EVADER).names()
    with pytest.raises(KeyError, match="threats"):
        s.layout(Role.PURSUER)["threats"]


def test_hash_is_stable_and_sensitive():
    a, b = SwarmSpec(), SwarmSpec()
    assert a.hash == b.hash and len(a.hash) == 12
    c = SwarmSpec.from_dict({"sensing": {"comm_range": 2.5}})
    d = SwarmSpec.from_dict({"team": {"n_scouts": 4}})
    assert len({a.hash, c.hash, d.hash}) == 3


def test_round_trip_through_dict():
    s = SwarmSpec.from_dict({"team": {"n_scouts": 0}, "pursuer": {"max_speed": 0.8}})
    assert SwarmSpec.from_dict(s.to_dict()) == s
    assert s.pursuer.radius == 0.075  # untouched fields keep their defaults


@pytest.mark.parametrize("data, field", [
    ({"arena": {"bogus": 1}}, "spec.arena.bogus"),
    ({"arena": {"half_width": "wide"}}, "spec.arena.half_width"),
    ({"arena": {"n_obstacles": 2.5}}, "spec.arena.n_obstacles"),
    ({"pursuer": {"radius": -0.1}}, "spec.pursuer.radius"),
    ({"arena": {"n_obstacles": 30}}, "spec.arena.n_obstacles"),
    ({"arena": {"obstacle_radius_min": 0.5, "obstacle_radius_max": 0.3}}, "spec.arena.obstacle_radius_max"),
    ({"sensing": {"observability": "some"}}, "spec.sensing.observability"),
    ({"timing": {"control_period": 0}}, "spec.timing.control_period"),
    ({"team": {"n_pursuers": 0, "n_scouts": 0}}, "spec.team"),
    ({"team": {"n_pursuers": 400}}, "spec.team"),
    ({"arena": {"obstacle_clearance": 0.1}}, "spec.arena.obstacle_clearance"),
    ({"sensing": {"sensing_range": math.inf}}, "spec.sensing.sensing_range"),
    ({"arena": []}, "spec.arena"),
    ({"avoidance": {"enabled": True, "teammate_braking": -1.0}}, "spec.avoidance.teammate_braking"),
    ({"avoidance": {"enabled": True, "braking": 3.0}}, "spec.avoidance.braking"),
    ({"avoidance": {"enabled": True, "teammate_braking": 6.0}}, "spec.avoidance.teammate_braking"),
    ({"avoidance": {"enabled": True, "teammate_credit": -0.1}}, "spec.avoidance.teammate_credit"),
    ({"avoidance": {"enabled": True, "teammate_credit": 1.5}}, "spec.avoidance.teammate_credit"),
    ({"avoidance": {"enabled": True, "teammate_credit": math.nan}}, "spec.avoidance.teammate_credit"),
])
def test_bad_values_name_the_field(data, field):
    with pytest.raises(SpecError) as info:
        SwarmSpec.from_dict(data)
    assert str(info.value).startswith(field), str(info.value)


def test_toml_files(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('name = "x"\n[spec.team]\nn_pursuers = 3\n[rewards]\ncapture_reward = 5.0\n')
    cfg = ExperimentConfig.from_toml(p)
    assert cfg.spec.team.n_pursuers == 3 and cfg.rewards.capture_reward == 5.0
    p.write_text("[spec.team]\nn_pursuer = 3\n")
    with pytest.raises(SpecError, match="n_pursuer: unknown key"):
        ExperimentConfig.from_toml(p)
    p.write_text("[spec\n")
    with pytest.raises(SpecError, match="not valid TOML"):
        load_toml(p)
    with pytest.raises(SpecError, match="does not exist"):
        load_toml(tmp_path / "missing.toml")


def test_shipped_configs_load():
    from pathlib import Path
    seen = 0
    for p in sorted(Path(__file__).resolve().parent.parent.glob("configs/*.toml")):
        if p.name in ("lps_anchors.toml", "fence.toml") or p.name.startswith(("fleet", "sweep")):
            continue  # ground-station and sweep files have loaders (and tests) of their own
        if "flight" in load_toml(p) and "train" not in load_toml(p):
            _load_flight_config(p)  # a `swarm-gs demo --flight-config` file
            continue
        ExperimentConfig.from_toml(p)
        seen += 1
    assert seen >= 5  # role_based, multi_target, their paper_ twins and paper_flight at least


def _load_flight_config(path):
    """What ``swarm-gs demo --flight-config`` reads: the [flight] and [separation] tables."""
    from groundstation.flight import FlightConfig
    from groundstation.separation import SeparationConfig
    FlightConfig.from_toml(path)
    SeparationConfig.from_dict(load_toml(path).get("separation", {}))
