import numpy as np
import pytest

from runtime.spec import Role, SwarmSpec
from training.config import RewardConfig
from training.env import PursuitEnv, compute_rewards


def _dist(pos):
    return np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)


def _contacts(spec, pos):
    r = np.array(spec.per_agent("radius"))
    c = _dist(pos) <= r[:, None] + r[None]
    c &= ~np.eye(pos.shape[1], dtype=bool)
    return c


def test_rewards_match_the_paper_equations():
    spec = SwarmSpec.from_dict({"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 2}})
    cfg = RewardConfig()
    pos = np.array([[[2.9, 0.0], [0.0, 0.0], [-1.0, -1.0], [0.1, 0.0], [1.0, 2.5]]])
    # pursuer 1 touches evader 3 (0.1 <= 0.075 + 0.05)
    t = compute_rewards(spec, cfg, pos, _dist(pos), _contacts(spec, pos))
    bx = -(np.minimum(np.exp(3 * np.abs(pos[0, :, 0]) - 9), 10) + np.minimum(np.exp(3 * np.abs(pos[0, :, 1]) - 9), 10))
    assert np.allclose(t.boundary[0], bx)
    assert t.capture[0, 1] == 20.0 and t.capture[0, 0] == 0.0 and t.capture[0, 3] == -10.0
    assert t.capture[0, 4] == 0.0 and t.capture[0, 2] == 0.0
    d = _dist(pos)[0]
    assert t.distance[0, 0] == pytest.approx(-(d[0, 3] + d[0, 4]) / 2)
    assert t.distance[0, 2] == 0 and t.distance[0, 3] == 0
    assert (t.collision == 0).all()
    # scouts: minus the largest bounded Voronoi cell with every agent a seed
    from training.voronoi import bounded_cell_areas
    assert t.exploration[0, 2] == pytest.approx(-bounded_cell_areas(pos, 3.0).max())
    assert (t.exploration[0, [0, 1, 3, 4]] == 0).all()
    # teammates touching: -10 each
    pos2 = pos.copy()
    pos2[0, 2] = pos2[0, 0] - [0.1, 0.0]
    t2 = compute_rewards(spec, cfg, pos2, _dist(pos2), _contacts(spec, pos2))
    assert t2.collision[0, 0] == -10 and t2.collision[0, 2] == -10 and t2.collision[0, 1] == 0


def test_env_steps_resets_and_reports_final_obs():
    spec = SwarmSpec.from_dict({"timing": {"episode_steps": 10}})
    env = PursuitEnv(spec, n_envs=3, seed=0, track_metrics=True)
    obs = env.reset()
    assert obs.shape == (3, 12, spec.max_obs_dim)
    rng = np.random.default_rng(0)
    for t in range(10):
        obs, r, done, info = env.step(rng.uniform(-1, 1, (3, 12, 2)))
        assert r.shape == (3, 12) and np.isfinite(r).all()
    assert done.all() and info["final_obs"].shape == (3, 12, spec.max_obs_dim)
    assert (env.state.step == 0).all()
    assert len(info["episodes"]) == 3
    per_role = env.role_rewards(r)
    assert set(per_role) == {"pursuer", "scout", "evader"}


def test_env_is_deterministic_under_a_seed():
    spec = SwarmSpec()
    outs = []
    for _ in range(2):
        env = PursuitEnv(spec, n_envs=2, seed=11)
        env.reset()
        rng = np.random.default_rng(3)
        acc = []
        for _ in range(20):
            o, r, d, _ = env.step(rng.uniform(-1, 1, (2, 12, 2)))
            acc.append(r)
        outs.append(np.array(acc))
    assert np.array_equal(outs[0], outs[1])
