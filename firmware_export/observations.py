"""Observations to check and calibrate an exported actor with: uniform within the spec's per-field ranges, and
recorded from the simulator (``runtime.world`` under random actions, through the one observation encoder)."""
from __future__ import annotations

import numpy as np

from runtime.observation import encode_observations, new_knowledge, update_knowledge
from runtime.spec import Role, SwarmSpec
from runtime.world import World


def random_observations(spec: SwarmSpec, role: Role, n: int, seed: int = 0) -> np.ndarray:
    """``n`` observations uniform within the layout's per-index ranges, float32 ``[n, obs_dim]``."""
    lo, hi = spec.layout(role).bounds()
    return np.random.default_rng(seed).uniform(lo, hi, (n, len(lo))).astype(np.float32)


def recorded_observations(spec: SwarmSpec, role: Role, n: int, seed: int = 0, n_envs: int = 16) -> np.ndarray:
    """``n`` observations of agents of ``role`` recorded from the world under random actions (the encoder
    training and flight use), float32 ``[n, obs_dim]``."""
    world = World(spec, n_envs=n_envs, seed=seed)
    rng = np.random.default_rng(seed + 1)
    st = world.reset()
    knowledge = new_knowledge(spec, n_envs)
    who = np.array(spec.team.indices(role))
    dim = spec.obs_dim(role)
    rows: list[np.ndarray] = []
    got = 0
    while got < n:
        t = st.step * spec.timing.control_period
        update_knowledge(spec, knowledge, st.pos, st.vel, t)
        obs = encode_observations(spec, st.pos, st.vel, st.obstacle_pos, st.obstacle_radius, knowledge, t,
                                  observers=who)
        block = obs[..., :dim].reshape(-1, dim)
        rows.append(block)
        got += block.shape[0]
        world.step(rng.uniform(-1.0, 1.0, (n_envs, spec.n_agents, 2)))
        done = st.step >= spec.timing.episode_steps
        if done.any():
            world.reset(np.nonzero(done)[0])
            knowledge[done] = new_knowledge(spec, int(done.sum()))
    return np.concatenate(rows)[:n].astype(np.float32)


def parity_observations(spec: SwarmSpec, role: Role, n: int, seed: int = 0) -> np.ndarray:
    """Half random within the spec's ranges, half recorded from the simulator."""
    return np.concatenate([random_observations(spec, role, n - n // 2, seed),
                           recorded_observations(spec, role, n // 2, seed)])
