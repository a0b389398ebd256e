"""training.pettingzoo_env: PettingZoo's own API and seed tests, plus what the wrapper promises on top."""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from runtime.spec import Role, SpecError, SwarmSpec
from training.pettingzoo_env import parallel_env

ROOT = Path(__file__).resolve().parent.parent
# a short episode keeps both PettingZoo tests to a few seconds; they still cross several truncations
SHORT = 40


def test_parallel_api_test_passes():
    env = parallel_env(config=ROOT / "configs/role_based.toml", max_cycles=SHORT)
    parallel_api_test(env, num_cycles=3 * SHORT)


def test_parallel_api_test_passes_on_the_multi_target_config():
    env = parallel_env(config=str(ROOT / "configs/multi_target.toml"), max_cycles=SHORT)
    parallel_api_test(env, num_cycles=2 * SHORT)


def test_parallel_seed_test_passes():
    parallel_seed_test(functools.partial(parallel_env, max_cycles=SHORT), num_cycles=2 * SHORT)


def _rollout(seed: int, steps: int) -> list[np.ndarray]:
    env = parallel_env(max_cycles=steps)
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(0)  # the same actions for every world seed
    out = [np.concatenate(list(obs.values()))]
    while env.agents:
        obs, rew, *_ = env.step({a: rng.uniform(-1, 1, 2) for a in env.agents})
        out += [np.concatenate(list(obs.values())), np.array(list(rew.values()))]
    return out


def test_same_seed_same_episode_other_seed_other_episode():
    # parallel_seed_test stops at its first step (it breaks on any(truncations), a non-empty dict), so the
    # whole-episode determinism is checked here
    a, b, c = _rollout(7, SHORT), _rollout(7, SHORT), _rollout(8, SHORT)
    assert len(a) == 2 * SHORT + 1
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[0], c[0])


def test_agents_spaces_and_observations_follow_the_spec():
    spec = SwarmSpec()
    env = parallel_env()
    obs, infos = env.reset(seed=3)
    assert env.possible_agents == list(spec.team.agent_ids())
    assert len(env.agents) == spec.n_agents == 12
    names_by_role = {r: [a for a, role in zip(env.possible_agents, spec.roles) if role == r] for r in Role}
    assert [len(names_by_role[r]) for r in (Role.PURSUER, Role.SCOUT, Role.EVADER)] == [5, 5, 2]
    for agent, role in zip(env.possible_agents, spec.roles):
        space = env.observation_space(agent)
        assert space.shape == (spec.obs_dim(role),) and space.dtype == np.float32
        assert obs[agent].shape == space.shape and space.contains(obs[agent])
        assert env.action_space(agent).shape == (2,)
        assert env.action_space(agent).low.min() == -1.0 and env.action_space(agent).high.max() == 1.0
    assert env.state().shape == (4 * spec.n_agents + 3 * spec.arena.n_obstacles,)


def test_truncates_every_agent_together_after_max_cycles():
    env = parallel_env(max_cycles=5)
    env.reset(seed=0)
    for t in range(5):
        acts = {a: env.action_space(a).sample() for a in env.agents}
        _, rew, term, trunc, _ = env.step(acts)
        assert set(rew) == set(acts) and not any(term.values())
        assert all(trunc.values()) == (t == 4) and len(set(trunc.values())) == 1
    assert env.agents == []
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})


def test_runs_to_the_spec_episode_length_and_counts_nan_actions():
    spec = SwarmSpec.from_dict({"timing": {"episode_steps": 12}})
    env = parallel_env(spec=spec)
    assert env.max_cycles == 12
    env.reset(seed=1)
    steps = 0
    while env.agents:
        acts = {a: np.array([np.nan, 0.2], dtype=np.float32) for a in env.agents}
        obs, *_ = env.step(acts)
        steps += 1
        assert all(np.isfinite(o).all() for o in obs.values())
    assert steps == 12
    # one NaN entry per agent per step becomes a zero command and is counted by the world
    assert env._env.world.nonfinite_actions == 12 * spec.n_agents


def test_bad_arguments_are_clear_errors(tmp_path):
    with pytest.raises(KeyError, match="unknown agent"):
        env = parallel_env()
        env.reset(seed=0)
        env.step({"pilot_0": [0.0, 0.0]})
    with pytest.raises(ValueError, match="render_mode"):
        parallel_env(render_mode="human")
    with pytest.raises(ValueError, match="either config or spec"):
        parallel_env(config=ROOT / "configs/role_based.toml", spec=SwarmSpec())
    with pytest.raises(SpecError, match="spec.team.n_scout"):
        parallel_env(spec={"team": {"n_scout": 2}})
    bad = tmp_path / "bad.toml"
    bad.write_text("[spec.arena]\nhalf_width = -1.0\n")
    with pytest.raises(SpecError, match="half_width"):
        parallel_env(config=bad)


def test_render_rgb_array():
    env = parallel_env(max_cycles=3, render_mode="rgb_array")
    env.reset(seed=0)
    env.step({a: env.action_space(a).sample() for a in env.agents})
    img = env.render()
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8 and img.std() > 0
