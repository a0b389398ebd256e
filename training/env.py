"""The vectorized pursuit-evasion-exploration environment: world + knowledge + observations + rewards.

Rewards are the paper's, per agent (equations 1-5 and Algorithm 1, constants in ``RewardConfig``):

- every agent: boundary ``B_i = -min(exp(3|x|-9), c1) - min(exp(3|y|-9), c2)`` and collision
  ``C_i = -c3`` per other agent within ``R_i + R_j`` (teammates; evader-evader);
- pursuers: ``R_p = B + C + CR_p + DR_p`` with ``CR_p = +20`` per evader touched and
  ``DR_p = -mean distance to the evaders``;
- evaders: ``R_e = B + C + CR_e`` with ``CR_e = -10`` per pursuer or scout touching it;
- scouts: ``R_s = B + C + E`` with ``E = -max bounded Voronoi cell area``, every agent a seed.

Options beyond the paper, each off by default (``RewardConfig``): an obstacle-contact penalty, a soft
teammate-proximity penalty, a team-aligned distance term, a shared capture reward, the pursuers' boundary
term off.

Episodes end by time limit only (``spec.timing.episode_steps``); finished envs are reset automatically and
their last observation is returned in ``info["final_obs"]`` (for bootstrapping, a time limit is not a
terminal state).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.observation import encode_observations, new_knowledge, update_knowledge
from runtime.spec import Role, SwarmSpec
from runtime.world import World
from training.config import RewardConfig


@dataclass
class RewardTerms:
    """Per-agent reward components ``[B, N]`` (zero where a term does not apply to the role)."""

    boundary: np.ndarray
    collision: np.ndarray
    capture: np.ndarray
    distance: np.ndarray
    exploration: np.ndarray

    def total(self) -> np.ndarray:
        return self.boundary + self.collision + self.capture + self.distance + self.exploration


def compute_rewards(spec: SwarmSpec, cfg: RewardConfig, pos: np.ndarray, dist: np.ndarray, contacts: np.ndarray,
                    obstacle_contacts: np.ndarray | None = None) -> RewardTerms:
    """Pure reward function of one step: positions ``[B, N, 2]``, distances and contacts ``[B, N, N]``."""
    team = spec.team
    nt, n = team.n_team, team.n_agents
    b = pos.shape[0]
    off = cfg.boundary_gain * spec.arena.half_width
    ax = np.abs(pos)
    boundary = -(np.minimum(np.exp(cfg.boundary_gain * ax[..., 0] - off), cfg.boundary_c1)
                 + np.minimum(np.exp(cfg.boundary_gain * ax[..., 1] - off), cfg.boundary_c2))
    is_team = np.arange(n) < nt
    same_side = is_team[:, None] == is_team[None, :]
    collision = -cfg.collision_penalty * (contacts & same_side[None]).sum(-1)
    if obstacle_contacts is not None and cfg.obstacle_penalty:
        collision = collision - cfg.obstacle_penalty * obstacle_contacts
    if cfg.proximity_penalty and nt > 1:
        collision = collision - cfg.proximity_penalty * _proximity(spec, cfg, dist[:, :nt, :nt], nt, n)
    capture = np.zeros((b, n))
    distance = np.zeros((b, n))
    exploration = np.zeros((b, n))
    p = np.asarray(team.indices(Role.PURSUER))
    if p.size:
        if not cfg.pursuer_boundary:
            boundary[:, p] = 0.0
        touched = contacts[:, p, nt:]  # [B, P, E]
        if cfg.shared_capture:
            capture[:, p] = cfg.capture_reward * touched.any(1).sum(-1, keepdims=True)
        else:
            capture[:, p] = cfg.capture_reward * touched.sum(-1)
        pe = dist[:, p, nt:]  # [B, P, E]
        if cfg.distance_mode == "team":
            distance[:, p] = -cfg.distance_weight * pe.min(1).mean(-1, keepdims=True)
            distance[:, p] -= cfg.own_distance_weight * pe.min(-1)
        else:
            distance[:, p] = -cfg.distance_weight * pe.mean(-1)
    capture[:, nt:] = -cfg.captured_penalty * contacts[:, nt:, :nt].sum(-1)
    sc = np.asarray(team.indices(Role.SCOUT))
    if sc.size:
        from training.voronoi import bounded_cell_areas
        areas = bounded_cell_areas(pos, spec.arena.half_width)
        exploration[:, sc] = -cfg.exploration_weight * areas.max(-1, keepdims=True)
    return RewardTerms(boundary, collision.astype(np.float64), capture, distance, exploration)


def _proximity(spec: SwarmSpec, cfg: RewardConfig, dist: np.ndarray, nt: int, n: int) -> np.ndarray:
    """[B, N]: per team agent, the sum over teammates of a ramp from 0 at ``proximity_distance`` to 1 at
    contact; zero for evaders."""
    radius = np.asarray(spec.per_agent("radius"))[:nt]
    touch = radius[:, None] + radius[None, :]
    span = np.maximum(cfg.proximity_distance - touch, 1e-9)
    ramp = np.clip((cfg.proximity_distance - dist) / span, 0.0, 1.0)
    ramp[:, np.arange(nt), np.arange(nt)] = 0.0
    out = np.zeros(dist.shape[:1] + (n,))
    out[:, :nt] = ramp.sum(-1)
    return out


class PursuitEnv:
    """``n_envs`` pursuit-evasion-exploration episodes stepped together.

    ``reset() -> obs`` and ``step(actions) -> (obs, rewards, done, info)`` with ``obs`` ``[B, N, D]``
    (``D = spec.max_obs_dim``; rows of roles with a shorter layout are zero-padded), ``actions`` ``[B, N, 2]``
    in [-1, 1], ``rewards`` ``[B, N]`` and ``done`` ``[B]``.
    """

    def __init__(self, spec: SwarmSpec, rewards: RewardConfig | None = None, n_envs: int = 1,
                 seed: int | None = None, track_metrics: bool = False) -> None:
        self.spec = spec
        self.reward_cfg = rewards or RewardConfig()
        self.n_envs = n_envs
        self.world = World(spec, n_envs, seed)
        self.knowledge = new_knowledge(spec, n_envs)
        self.n_agents = spec.n_agents
        self.obs_dim = spec.max_obs_dim
        self.roles = spec.roles
        self.agent_ids = spec.team.agent_ids()
        self.metrics = None
        if track_metrics:
            from runtime.metrics import MetricsAccumulator
            self.metrics = MetricsAccumulator(spec, n_envs)
        self._obs = np.zeros((n_envs, self.n_agents, self.obs_dim))
        self.last_terms: RewardTerms | None = None

    @property
    def state(self):
        return self.world.state

    def time_s(self) -> np.ndarray:
        return self.world.state.step * self.spec.timing.control_period

    def reset(self, env_ids: np.ndarray | None = None) -> np.ndarray:
        """Reset all envs (or ``env_ids``) and return the observations of all envs."""
        ids = np.arange(self.n_envs) if env_ids is None else np.asarray(env_ids, dtype=np.int64)
        self._reset_ids(ids)
        return self._observe()

    def _reset_ids(self, ids: np.ndarray) -> None:
        self.world.reset(ids)
        self.restart(ids)

    def restart(self, ids: np.ndarray) -> None:
        """Start new episodes in ``ids`` from the world's current state: target knowledge and metrics anew, the
        world untouched (for states set from outside, e.g. copied between envs); ``observe()`` gives their
        observations."""
        s = self.world.state
        self.knowledge[ids] = new_knowledge(self.spec, ids.size)
        sub = update_knowledge(self.spec, self.knowledge[ids], s.pos[ids], s.vel[ids], 0.0)
        self.knowledge[ids] = sub
        if self.metrics is not None:
            self.metrics.begin_episodes(ids, s.obstacle_pos[ids], s.obstacle_radius[ids])

    def observe(self) -> np.ndarray:
        """The observations of every env now ``[B, N, D]``."""
        return self._observe()

    def _observe(self, dist: np.ndarray | None = None) -> np.ndarray:
        s = self.world.state
        return encode_observations(self.spec, s.pos, s.vel, s.obstacle_pos, s.obstacle_radius, self.knowledge,
                                   self.time_s(), dist=dist, out=self._obs).copy()

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
        w = self.world
        contacts = w.step(actions)
        s = w.state
        dist = w.last_distances
        obstacle_contacts = w.obstacle_contacts()
        terms = compute_rewards(self.spec, self.reward_cfg, s.pos, dist, contacts, obstacle_contacts)
        self.last_terms = terms
        update_knowledge(self.spec, self.knowledge, s.pos, s.vel, self.time_s(), dist)
        if self.metrics is not None:
            self.metrics.update(s.pos, contacts, obstacle_contacts, dist)
        obs = self._observe(dist)
        done = s.step >= self.spec.timing.episode_steps
        info: dict = {"contacts": contacts, "obstacle_contacts": obstacle_contacts}
        if done.any():
            ids = np.nonzero(done)[0]
            info["final_obs"] = obs[ids].copy()
            info["final_env_ids"] = ids
            if self.metrics is not None:
                info["episodes"] = self.metrics.end_episodes(ids)
            self._reset_ids(ids)
            obs[ids] = self._observe()[ids]
        return obs, terms.total(), done, info

    def role_rewards(self, rewards: np.ndarray) -> dict[str, np.ndarray]:
        """Per-role mean reward ``{role: [B]}`` from per-agent rewards ``[B, N]``."""
        out = {}
        for r in Role:
            idx = list(self.spec.team.indices(r))
            if idx:
                out[r.label] = rewards[:, idx].mean(-1)
        return out
