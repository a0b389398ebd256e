"""World + rewards (Voronoi included) and the full env step, 12 agents (5 pursuers, 5 scouts, 2 evaders),
3 obstacles, at n_envs 1, 256 and 1024. Target on 2 cores: >= 50,000 env-steps/s at 1024 envs.

Run: .venv/bin/python -m pytest tests/benchmarks/test_bench_env.py --benchmark-enable
"""
import numpy as np
import pytest

from runtime.spec import SwarmSpec
from runtime.world import World
from training.config import RewardConfig
from training.env import PursuitEnv, compute_rewards


@pytest.mark.parametrize("n_envs", [1, 256, 1024])
def test_world_and_rewards(benchmark, n_envs):
    spec, cfg = SwarmSpec(), RewardConfig()
    w = World(spec, n_envs, seed=0)
    w.reset()
    actions = np.random.default_rng(1).uniform(-1, 1, (n_envs, spec.n_agents, 2))

    def step():
        contacts = w.step(actions)
        return compute_rewards(spec, cfg, w.state.pos, w.last_distances, contacts, w.obstacle_contacts())

    step()  # numba compile outside the timing
    terms = benchmark(step)
    assert terms.total().shape == (n_envs, spec.n_agents) and np.isfinite(terms.total()).all()
    if benchmark.stats:
        med = benchmark.stats.stats.median
        benchmark.extra_info["env_steps_per_s"] = n_envs / med
        benchmark.extra_info["us_per_env_step"] = med / n_envs * 1e6


@pytest.mark.parametrize("n_envs", [1, 1024])
def test_full_env_step_with_observations(benchmark, n_envs):
    env = PursuitEnv(SwarmSpec(), n_envs=n_envs, seed=0)
    env.reset()
    actions = np.random.default_rng(1).uniform(-1, 1, (n_envs, env.n_agents, 2))
    env.step(actions)
    obs, r, done, info = benchmark(env.step, actions)
    assert obs.shape == (n_envs, env.n_agents, env.obs_dim)
    if benchmark.stats:
        benchmark.extra_info["env_steps_per_s"] = n_envs / benchmark.stats.stats.median
