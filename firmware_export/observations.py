"""Observations to check and calibrate an exported actor with, defined once (the ONNX export, the C export and
its report use these): uniform within the spec's per-field ranges (``random_observations``), and recorded from
the simulator (``runtime.world`` through the one observation encoder, ``simulate``) under random actions
(``recorded_observations``) or while the trained actors fly (``flown_observations``, in ``onnx_export``: it
needs torch)."""
from __future__ import annotations

from typing import Callable, Iterator

import numpy as np

from runtime.observation import encode_observations, new_knowledge, update_knowledge
from runtime.spec import Role, SwarmSpec
from runtime.world import World


def random_observations(spec: SwarmSpec, role: Role, n: int, seed: int | np.random.Generator = 0) -> np.ndarray:
    """``n`` observations uniform within the layout's per-index ranges, float32 ``[n, obs_dim]``; ``seed`` an
    int or a generator to draw from."""
    lo, hi = spec.layout(role).bounds()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    return rng.uniform(lo, hi, (n, len(lo))).astype(np.float32)


def simulate(spec: SwarmSpec, n_envs: int, seed: int, act: Callable[[np.ndarray], np.ndarray],
             observers: np.ndarray | None = None) -> Iterator[np.ndarray]:
    """Every control period's observations ``[n_envs, n_observers, max_obs_dim]`` (float64, the encoder
    training and flight use, with relayed target knowledge) of ``n_envs`` worlds seeded ``seed``, stepped with
    ``act(observations) -> actions [n_envs, n_agents, 2]``; an env whose episode ends is reset. Endless: take
    what you need."""
    world = World(spec, n_envs=n_envs, seed=seed)
    s = world.reset()
    knowledge = new_knowledge(spec, n_envs)
    while True:
        t = s.step * spec.timing.control_period
        update_knowledge(spec, knowledge, s.pos, s.vel, t)
        obs = encode_observations(spec, s.pos, s.vel, s.obstacle_pos, s.obstacle_radius, knowledge, t,
                                  observers=observers)
        yield obs
        world.step(act(obs))
        done = s.step >= spec.timing.episode_steps
        if done.any():
            ids = np.nonzero(done)[0]
            world.reset(ids)
            knowledge[ids] = new_knowledge(spec, ids.size)


def recorded_observations(spec: SwarmSpec, role: Role, n: int, seed: int = 0, n_envs: int = 16) -> np.ndarray:
    """``n`` observations of agents of ``role`` recorded from the world under random actions (seeded
    ``seed + 1``), float32 ``[n, obs_dim]``."""
    rng = np.random.default_rng(seed + 1)
    dim = spec.obs_dim(role)
    rows: list[np.ndarray] = []
    got = 0
    for obs in simulate(spec, n_envs, seed, lambda _: rng.uniform(-1.0, 1.0, (n_envs, spec.n_agents, 2)),
                        observers=np.array(spec.team.indices(role))):
        if got >= n:
            break
        block = obs[..., :dim].reshape(-1, dim)
        rows.append(block)
        got += block.shape[0]
    return np.concatenate(rows)[:n].astype(np.float32)


def parity_observations(spec: SwarmSpec, role: Role, n: int, seed: int = 0,
                        recorded_seed: int | None = None) -> np.ndarray:
    """Half random within the spec's ranges (``seed``), half recorded from the simulator (``recorded_seed``,
    default ``seed``)."""
    return np.concatenate([random_observations(spec, role, n - n // 2, seed),
                           recorded_observations(spec, role, n // 2, seed if recorded_seed is None else recorded_seed)])
