"""The reward options beyond the paper (RewardConfig): each computed as documented, each off by default."""
import dataclasses

import numpy as np
import pytest

from runtime.spec import SpecError, SwarmSpec
from training.config import RewardConfig
from training.env import compute_rewards

SPEC = SwarmSpec.from_dict({"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 2}})
# pursuers 0, 1, scout 2, evaders 3, 4; pursuer 1 touches evader 3
POS = np.array([[[2.9, 0.0], [0.0, 0.0], [-1.0, -1.0], [0.1, 0.0], [1.0, 2.5]]])


def _dist(pos):
    return np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)


def _contacts(pos):
    r = np.array(SPEC.per_agent("radius"))
    c = _dist(pos) <= r[:, None] + r[None]
    c &= ~np.eye(pos.shape[1], dtype=bool)
    return c


def _terms(cfg, pos=POS, obstacle_contacts=None):
    return compute_rewards(SPEC, cfg, pos, _dist(pos), _contacts(pos), obstacle_contacts)


def test_defaults_are_the_paper():
    cfg = RewardConfig()
    assert (cfg.distance_mode, cfg.shared_capture, cfg.pursuer_boundary) == ("mean", False, True)
    assert cfg.proximity_penalty == 0 and cfg.obstacle_penalty == 0 and cfg.own_distance_weight == 0


def test_team_distance_is_the_mean_over_evaders_of_the_nearest_pursuer():
    d = _dist(POS)[0]
    t = _terms(RewardConfig(distance_mode="team"))
    nearest = np.mean([min(d[0, 3], d[1, 3]), min(d[0, 4], d[1, 4])])
    assert t.distance[0, 0] == pytest.approx(-nearest) and t.distance[0, 1] == pytest.approx(-nearest)
    assert (t.distance[0, 2:] == 0).all()
    t2 = _terms(RewardConfig(distance_mode="team", own_distance_weight=0.5))
    assert t2.distance[0, 0] == pytest.approx(-nearest - 0.5 * min(d[0, 3], d[0, 4]))


def test_shared_capture_pays_every_pursuer():
    t = _terms(RewardConfig(shared_capture=True))
    assert t.capture[0, 0] == 20.0 and t.capture[0, 1] == 20.0 and t.capture[0, 2] == 0.0
    assert t.capture[0, 3] == -10.0  # the evader's side is unchanged


def test_pursuer_boundary_off_leaves_the_others():
    on, off = _terms(RewardConfig()), _terms(RewardConfig(pursuer_boundary=False))
    assert on.boundary[0, 0] < 0 and off.boundary[0, 0] == 0 and off.boundary[0, 1] == 0
    assert np.array_equal(on.boundary[0, 2:], off.boundary[0, 2:])


def test_obstacle_penalty_while_touching():
    oc = np.array([[False, True, False, False, True]])
    t = _terms(RewardConfig(obstacle_penalty=3.0), obstacle_contacts=oc)
    assert t.collision[0, 1] == -3.0 and t.collision[0, 4] == -3.0 and t.collision[0, 0] == 0


def test_proximity_ramp_from_its_distance_to_contact():
    cfg = RewardConfig(proximity_penalty=2.0, proximity_distance=0.35)
    for gap, ramp in ((0.40, 0.0), (0.35, 0.0), (0.25, 0.5), (0.16, 0.95)):
        pos = POS.copy()
        pos[0, 2] = pos[0, 1] + [0.0, gap]  # the scout next to pursuer 1
        t = _terms(cfg, pos)
        assert t.collision[0, 1] == pytest.approx(-2.0 * ramp) and t.collision[0, 2] == pytest.approx(-2.0 * ramp)
        assert t.collision[0, 0] == 0 and (t.collision[0, 3:] == 0).all()


@pytest.mark.parametrize("field, value, fix", [("distance_mode", "nearest", "'mean', 'team'"),
                                               ("proximity_penalty", -1.0, ">= 0"),
                                               ("own_distance_weight", 1.0, "distance_mode = 'team'")])
def test_bad_options_name_the_field(field, value, fix):
    with pytest.raises(SpecError, match=f"rewards.{field}.*{fix}"):
        dataclasses.replace(RewardConfig(), **{field: value})
