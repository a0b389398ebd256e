"""The environment behind PettingZoo's standard ``ParallelEnv`` interface (one env, agents by name).

    from training.pettingzoo_env import parallel_env
    env = parallel_env(config="configs/role_based.toml")
    obs, infos = env.reset(seed=0)
    obs, rewards, terminations, truncations, infos = env.step({a: env.action_space(a).sample() for a in env.agents})

It wraps ``training.env.PursuitEnv`` with ``n_envs = 1``: the same world, observation encoder and rewards.
Agents are named ``pursuer_k``, ``scout_k``, ``evader_k``. Each agent's observation is its own role's layout
(``spec.obs_dim(role)`` float32 values, not the batch's zero-padded width) in a ``Box`` whose bounds are
``spec.layout(role).bounds()``; the action is a normalized velocity command in ``Box(-1, 1, (2,), float32)``.
Episodes never terminate; every agent is truncated together after ``max_cycles`` steps (at most
``spec.timing.episode_steps``, the world's episode length, which is part of the spec).
"""
from __future__ import annotations

import functools
import logging
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from runtime.spec import SwarmSpec
from training.config import ExperimentConfig, RewardConfig
from training.env import PursuitEnv

log = logging.getLogger(__name__)

__all__ = ["PursuitParallelEnv", "parallel_env"]


class PursuitParallelEnv(ParallelEnv):
    metadata = {"name": "swarmpursuit_v0", "render_modes": ["rgb_array"], "is_parallelizable": True,
                "render_fps": 10}

    def __init__(self, spec: SwarmSpec, rewards: RewardConfig | None = None, max_cycles: int | None = None,
                 render_mode: str | None = None) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r} is not supported: use None or 'rgb_array'")
        self.spec = spec
        self.rewards = rewards or RewardConfig()
        self.max_cycles = spec.timing.episode_steps if max_cycles is None else int(max_cycles)
        if self.max_cycles < 1:
            raise ValueError(f"max_cycles must be >= 1, got {self.max_cycles}")
        self.render_mode = render_mode
        self.possible_agents = list(spec.team.agent_ids())
        self.agents: list[str] = []
        self._role = dict(zip(self.possible_agents, spec.roles))
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self._dims = [spec.obs_dim(r) for r in spec.roles]
        self._env: PursuitEnv | None = None
        self._cycles = 0
        self._trail: list[np.ndarray] = []

    # -- spaces ------------------------------------------------------------------------------------
    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent: str) -> spaces.Box:
        lo, hi = self.spec.layout(self._role[agent]).bounds()
        return spaces.Box(np.array(lo, dtype=np.float32), np.array(hi, dtype=np.float32), dtype=np.float32)

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, (self.spec.act_dim,), dtype=np.float32)

    @property
    def observation_spaces(self) -> dict[str, spaces.Box]:
        return {a: self.observation_space(a) for a in self.possible_agents}

    @property
    def action_spaces(self) -> dict[str, spaces.Box]:
        return {a: self.action_space(a) for a in self.possible_agents}

    # -- episode -----------------------------------------------------------------------------------
    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None):
        """A new episode; ``seed`` re-seeds the world's generator (``None`` continues its stream)."""
        if self._env is None or seed is not None:
            self._env = PursuitEnv(self.spec, self.rewards, n_envs=1, seed=seed)
        obs = self._env.reset()
        self.agents = list(self.possible_agents)
        self._cycles = 0
        self._trail = [self._env.state.pos[0].copy()]
        return self._split(obs[0]), {a: {} for a in self.agents}

    def step(self, actions: Mapping[str, Any]):
        """Steps every live agent; agents missing from ``actions`` command zero velocity."""
        if self._env is None or not self.agents:
            raise RuntimeError("step() called before reset() or after the episode ended: call reset() first")
        a = np.zeros((1, self.spec.n_agents, 2))
        for name, act in actions.items():
            if name not in self._index:
                raise KeyError(f"unknown agent {name!r}: agents are {self.possible_agents}")
            a[0, self._index[name]] = np.asarray(act, dtype=np.float64).reshape(2)
        obs, rew, done, info = self._env.step(a)
        self._cycles += 1
        if done[0]:
            obs = info["final_obs"]  # the world has already started the next episode
            self._trail.append(obs[0, :, :2].copy())
        else:
            self._trail.append(self._env.state.pos[0].copy())
        truncated = bool(done[0]) or self._cycles >= self.max_cycles
        live = self.agents
        observations = self._split(obs[0])
        rewards = {n: float(rew[0, self._index[n]]) for n in live}
        terminations = {n: False for n in live}
        truncations = {n: truncated for n in live}
        infos: dict[str, dict] = {n: {} for n in live}
        if truncated:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def _split(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        out = {}
        for name in self.agents:
            i = self._index[name]
            space = self.observation_space(name)
            o = obs[i, : self._dims[i]].astype(np.float32)
            # the bounds hold by construction; the clip only absorbs float32 rounding at the edges
            out[name] = np.clip(o, space.low, space.high)
        return out

    def state(self) -> np.ndarray:
        """Global state for centralized critics: every agent's position and velocity, then every obstacle's
        centre and radius, float32."""
        if self._env is None:
            raise RuntimeError("state() called before reset()")
        s = self._env.state
        return np.concatenate([s.pos[0].ravel(), s.vel[0].ravel(), s.obstacle_pos[0].ravel(),
                               s.obstacle_radius[0].ravel()]).astype(np.float32)

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            log.warning("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        if self._env is None:
            raise RuntimeError("render() called before reset()")
        from training.plots import EpisodeTrace, render_rgb
        s = self._env.state
        trace = EpisodeTrace(self.spec, np.stack(self._trail), s.obstacle_pos[0].copy(), s.obstacle_radius[0].copy())
        return render_rgb(trace)

    def close(self) -> None:
        self._env = None


def parallel_env(config: str | Path | ExperimentConfig | None = None, spec: SwarmSpec | Mapping | None = None,
                 rewards: RewardConfig | Mapping | None = None, max_cycles: int | None = None,
                 render_mode: str | None = None) -> PursuitParallelEnv:
    """The PettingZoo ``ParallelEnv``.

    ``config``: an experiment TOML path or ``ExperimentConfig`` (its spec and rewards); or ``spec`` (a
    ``SwarmSpec`` or its dict) and ``rewards`` (a ``RewardConfig`` or its dict) directly; default: the default
    spec (5 pursuers, 5 scouts, 2 evaders) and the paper's rewards. ``max_cycles``: steps before truncation
    (default and maximum: ``spec.timing.episode_steps``). ``render_mode``: None or "rgb_array".
    """
    if config is not None and spec is not None:
        raise ValueError("pass either config or spec, not both")
    if config is not None:
        cfg = config if isinstance(config, ExperimentConfig) else ExperimentConfig.from_toml(config)
        spec = cfg.spec
        if rewards is None:
            rewards = cfg.rewards
    if spec is None:
        spec = SwarmSpec()
    elif not isinstance(spec, SwarmSpec):
        spec = SwarmSpec.from_dict(spec)
    if rewards is not None and not isinstance(rewards, RewardConfig):
        from runtime.spec import from_mapping
        rewards = from_mapping(RewardConfig, rewards, "rewards")
    return PursuitParallelEnv(spec, rewards, max_cycles=max_cycles, render_mode=render_mode)
