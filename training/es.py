"""Evolution strategies on the pursuer team's actors, scored on the evaluation's own metrics.

After imitation (and MADDPG, where it helps), the pursuer team's actors are improved by OpenAI-ES (Salimans et
al. 2017): each iteration draws ``population`` Gaussian directions ``eps`` in the space of the team's actor
weights (one actor per role: the pursuers share one, the scouts another, as with ``train.share_params``), flies
``theta + sigma eps`` and ``theta - sigma eps`` through ``episodes`` whole episodes each, and steps ``theta``
along the rank-weighted differences with Adam. What is scored is what the evaluation reports
(``runtime.metrics``), per episode:

    fitness = tracking_rate x es_tracking_weight - mean_min_dist x es_distance_weight
              + coverage x es_coverage_weight - team_contacts x es_contact_weight
              + captures x es_capture_weight

With ``train.es_role_fitness`` each role's block of weights ascends its own part of it, from the same rollouts:
the pursuers' everything but the coverage term, the scouts' the coverage and contact terms ("split") or the whole
("pursuers").

Every member of a population meets the same episodes (common random numbers: the same starts, obstacles and
evaders with the same drawn parameters), so a difference in fitness is a difference in the actors, not in
luck. The actors fly through the spec's avoidance layer as on the drone. Opponents: the held-out suite and the
scripted fleeing evaders are never met; each env draws its evaders from the training pool
(``training.evader_suite.TrainingPool``) or, with probability ``es_learned_share``, the run's own co-trained
evader actors (frozen).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from runtime.avoidance import avoid_agents
from runtime.spec import Role, SwarmSpec
from training.env import PursuitEnv
from training.evader_suite import TrainingPool
from training.networks import Actor

log = logging.getLogger(__name__)

ES_COLUMNS = ("iteration", "time_s", "fitness", "fitness_best", "min_dist", "tracking", "coverage",
              "team_contacts", "sigma", "step_norm")
"""``es.csv``: per iteration the fitness and metrics of the weights before the step (the centre, flown on the
population's episodes), the best member's fitness, and the step's norm."""


@dataclass
class RoleActor:
    """One role's actor as flat float64 weights, and how to unflatten them: layers of ``(in, out)``."""

    role: Role
    agents: list[int]
    obs_dim: int
    shapes: list[tuple[int, int]]
    theta: np.ndarray

    @classmethod
    def from_actor(cls, role: Role, agents: list[int], actor: Actor) -> "RoleActor":
        lin = [m for m in actor.net if isinstance(m, torch.nn.Linear)]
        shapes = [(m.in_features, m.out_features) for m in lin]
        flat = [np.concatenate([m.weight.detach().double().numpy().T.ravel(), m.bias.detach().double().numpy()])
                for m in lin]
        return cls(role, agents, actor.obs_dim, shapes, np.concatenate(flat))

    def to_actor(self, theta: np.ndarray | None = None) -> Actor:
        t = self.theta if theta is None else theta
        hidden = tuple(o for _, o in self.shapes[:-1])
        actor = Actor(self.obs_dim, self.shapes[-1][1], hidden)
        lin = [m for m in actor.net if isinstance(m, torch.nn.Linear)]
        k = 0
        with torch.no_grad():
            for m, (i, o) in zip(lin, self.shapes):
                m.weight.copy_(torch.as_tensor(t[k:k + i * o].reshape(i, o).T))
                k += i * o
                m.bias.copy_(torch.as_tensor(t[k:k + o]))
                k += o
        return actor

    def layers(self, thetas: np.ndarray) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Weights ``[G, in, out]`` and biases ``[G, 1, out]`` of ``G`` flat weight vectors ``[G, P]``."""
        g = thetas.shape[0]
        out, k = [], 0
        t = torch.as_tensor(thetas, dtype=torch.float32)
        for i, o in self.shapes:
            out.append((t[:, k:k + i * o].reshape(g, i, o), t[:, k + i * o:k + i * o + o].reshape(g, 1, o)))
            k += i * o + o
        return out


def mlp_forward(x: torch.Tensor, layers: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """``[G, M, in] -> [G, M, out]``: ReLU hidden layers, tanh output (the ``Actor`` contract)."""
    last = len(layers) - 1
    for k, (w, b) in enumerate(layers):
        x = torch.baddbmm(b, x, w)
        x = torch.relu(x) if k < last else torch.tanh(x)
    return x


class _FrozenEvaders:
    """The run's co-trained evader actors, through the avoidance layer, for the evader columns."""

    def __init__(self, spec: SwarmSpec, actors: list[Actor], agents: list[int]) -> None:
        self.spec, self.actors, self.agents = spec, actors, agents

    @torch.no_grad()
    def act(self, obs: np.ndarray, env: Any) -> np.ndarray:
        out = np.zeros(obs.shape[:2] + (2,))
        for i, a in zip(self.agents, self.actors):
            out[:, i] = a(torch.as_tensor(obs[:, i, :a.obs_dim], dtype=torch.float32)).double().numpy()
        return avoid_agents(self.spec, obs, out, self.agents)


class _Opponents:
    """Per env: the training pool's evaders, or (share ``learned_share``) the frozen co-trained ones."""

    def __init__(self, pool: TrainingPool, frozen: _FrozenEvaders | None, learned: np.ndarray) -> None:
        self.pool, self.frozen, self.learned = pool, frozen, learned

    def act(self, obs: np.ndarray, env: Any) -> np.ndarray:
        out = self.pool.act(obs, env)
        if self.frozen is not None and self.learned.any():
            out[self.learned] = self.frozen.act(obs[self.learned], env)
        return out


def _tile(arr: np.ndarray, e: int) -> None:
    """In place: every block of ``e`` rows becomes a copy of the first block."""
    b = arr.shape[0]
    arr[:] = np.tile(arr[:e], (b // e,) + (1,) * (arr.ndim - 1))


def _tile_pool(pool: TrainingPool, e: int) -> None:
    """The pool's per-env draws (behaviour and each behaviour's parameters and state) copied from the first
    block of ``e`` envs to every other block."""
    _tile(pool.choice, e)
    for beh in pool.behaviours:
        for v in beh.p.values():
            _tile(v, e)


class TeamES:
    """ES over the team's role actors of a run (``actors``: every agent's ``Actor`` in spec order)."""

    def __init__(self, spec: SwarmSpec, rewards: Any, actors: list[Actor], tc: Any, seed: int) -> None:
        self.spec, self.rewards, self.tc = spec, rewards, tc
        roles = list(spec.roles)
        nt = spec.team.n_team
        self.roles = [RoleActor.from_actor(r, [i for i in range(nt) if roles[i] is r],
                                           actors[roles.index(r)]) for r in (Role.PURSUER, Role.SCOUT)
                      if r in roles[:nt]]
        ev = [i for i in range(spec.n_agents) if roles[i] is Role.EVADER]
        self.frozen = _FrozenEvaders(spec, [actors[i] for i in ev], ev)
        self.evader_actors = [actors[i] for i in ev]
        self.rng = np.random.default_rng(seed)
        self.sizes = [r.theta.size for r in self.roles]
        self.theta = np.concatenate([r.theta for r in self.roles])
        self._m = np.zeros_like(self.theta)
        self._v = np.zeros_like(self.theta)
        self.iteration = 0

    # ---------------------------------------------------------------------------------------- scoring
    def _split(self, thetas: np.ndarray) -> list[np.ndarray]:
        return np.split(thetas, np.cumsum(self.sizes)[:-1], axis=1)

    def rollout(self, thetas: np.ndarray, episodes: int, seed: int) -> list[list[Any]]:
        """Every weight vector of ``thetas`` ``[G, P]`` flown through the same ``episodes`` episodes; returns the
        episode records per member."""
        g, e = thetas.shape[0], episodes
        spec, nt = self.spec, self.spec.team.n_team
        env = PursuitEnv(spec, self.rewards, n_envs=g * e, seed=seed, track_metrics=True)
        rng = np.random.default_rng(seed + 1)
        env.reset()
        s = env.world.state
        for a in (s.pos, s.vel, s.obstacle_pos, s.obstacle_radius):
            _tile(a, e)  # common random numbers: every member meets the first block's episodes
        env.restart(np.arange(g * e))
        obs = env.observe()
        learned = np.tile(rng.random(e) < self.tc.es_learned_share, g)
        pool = TrainingPool(seed=seed + 2, kinds=list(self.tc.es_pool) or None)
        opponents = _Opponents(pool, self.frozen if self.evader_actors else None, learned)
        layers = [r.layers(t) for r, t in zip(self.roles, self._split(thetas))]
        act = np.zeros((g * e, spec.n_agents, 2))
        for step in range(spec.timing.episode_steps):
            with torch.no_grad():
                for r, lay in zip(self.roles, layers):
                    x = torch.as_tensor(obs[:, r.agents, :r.obs_dim], dtype=torch.float32)
                    y = mlp_forward(x.reshape(g, e * len(r.agents), r.obs_dim), lay)
                    act[:, r.agents] = y.reshape(g * e, len(r.agents), 2).double().numpy()
            avoid_agents(spec, obs, act, np.arange(nt))
            ev = opponents.act(obs, env)
            if step == 0:
                _tile_pool(pool, e)
                ev = opponents.act(obs, env)  # the same draws in every block (the pool keeps its step-0 draws)
            act[:, nt:] = ev[:, nt:]
            obs, _, done, info = env.step(act)
        recs = info["episodes"]
        return [recs[k * e:(k + 1) * e] for k in range(g)]

    def episode_fitness(self, records: list[Any], role: Role | None = None) -> np.ndarray:
        """The fitness of each episode record: the team's, or with ``role`` (``train.es_role_fitness``) that role's
        part of it: the pursuers' without the coverage term, the scouts' coverage and contacts."""
        tc = self.tc
        pursuit = role is not Role.SCOUT
        cover = role is not Role.PURSUER
        return np.array([pursuit * (tc.es_tracking_weight * r.tracking_rate - tc.es_distance_weight * r.min_dist
                                    + tc.es_capture_weight * r.captures)
                         + cover * tc.es_coverage_weight * r.coverage - tc.es_contact_weight * r.team_contacts
                         for r in records], dtype=np.float64)

    def fitness(self, records: list[Any]) -> float:
        """The mean of ``episode_fitness`` over the records."""
        return float(self.episode_fitness(records).mean())

    def ranking_scores(self, per_member: list[list[Any]], role: Role | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(what the members are ranked by, their mean fitness; ``role``: that role's, ``episode_fitness``). Ranked
        by (``train.es_rank``): their mean fitness ("total"), or their mean rank within each episode ("episode":
        every episode has the same say, whatever its opponent's scale)."""
        f = np.stack([self.episode_fitness(r, role) for r in per_member])  # [members, episodes]
        mean = f.mean(1)
        if self.tc.es_rank == "episode":
            return f.argsort(0, kind="stable").argsort(0, kind="stable").mean(1), mean
        return mean, mean

    # ----------------------------------------------------------------------------------------- update
    def step(self) -> dict[str, float]:
        """One ES iteration; returns its figures (``ES_COLUMNS``)."""
        tc = self.tc
        p, sig = tc.es_population, tc.es_sigma
        eps = self.rng.standard_normal((p, self.theta.size))
        frozen = self._frozen()
        eps[:, frozen] = 0.0  # a frozen role flies its centre in every member
        # the centre flies too (last member): its figures are the ones logged, on the population's episodes
        thetas = np.concatenate([self.theta + sig * eps, self.theta - sig * eps, self.theta[None]])
        seed = int(self.rng.integers(2 ** 31))
        per_member = self.rollout(thetas, tc.es_episodes, seed)
        centre = per_member.pop()
        f, fit = self.ranking_scores(per_member)
        if tc.es_role_fitness != "team":  # each role's block of weights along its own fitness's ranks
            own = {Role.PURSUER: Role.PURSUER, Role.SCOUT: Role.SCOUT if tc.es_role_fitness == "split" else None}
            grad = np.concatenate([self._ascent(f if own[r.role] is None else
                                                self.ranking_scores(per_member, own[r.role])[0], e, sig)
                                   for r, e in zip(self.roles, self._split(eps))])
        else:
            grad = self._ascent(f, eps, sig)
        # Adam ascent
        self.iteration += 1
        b1, b2 = 0.9, 0.999
        self._m = b1 * self._m + (1 - b1) * grad
        self._v = b2 * self._v + (1 - b2) * grad * grad
        mh = self._m / (1 - b1 ** self.iteration)
        vh = self._v / (1 - b2 ** self.iteration)
        stepv = tc.es_lr * mh / (np.sqrt(vh) + 1e-8)
        stepv[frozen] = 0.0
        self.theta = self.theta + stepv
        recs = centre
        return {"iteration": self.iteration, "fitness": self.fitness(centre), "fitness_best": float(fit.max()),
                "min_dist": float(np.mean([r.min_dist for r in recs])),
                "tracking": float(np.mean([r.tracking_rate for r in recs])),
                "coverage": float(np.mean([r.coverage for r in recs])),
                "team_contacts": float(np.mean([r.team_contacts for r in recs])), "sigma": sig,
                "step_norm": float(np.linalg.norm(stepv))}

    def _frozen(self) -> np.ndarray:
        """Mask over ``theta`` of the weights this iteration leaves alone: the pursuers' once ``es_pursuer_iterations``
        iterations have moved them (``train.es_pursuer_iterations``)."""
        mask = np.zeros((1, self.theta.size), dtype=bool)
        k = self.tc.es_pursuer_iterations
        if k is not None and self.iteration >= k:
            for r, block in zip(self.roles, self._split(mask)):  # views of the mask, role by role
                block[:] = r.role is Role.PURSUER
        return mask[0]

    @staticmethod
    def _ascent(f: np.ndarray, eps: np.ndarray, sig: float) -> np.ndarray:
        """The antithetic estimate of the fitness gradient from the members' scores ``f`` [2P] (the +sigma
        members, then the -sigma ones) and their directions ``eps`` [P, n], by centred ranks."""
        p = eps.shape[0]
        ranks = np.empty(2 * p)
        ranks[np.argsort(f)] = np.arange(2 * p)
        u = ranks / (2 * p - 1) - 0.5  # centred ranks
        return ((u[:p] - u[p:])[:, None] * eps).sum(0) / (2 * p * sig)

    def state_dict(self) -> dict[str, Any]:
        return {"theta": self.theta.copy(), "m": self._m.copy(), "v": self._v.copy(), "iteration": self.iteration,
                "rng": self.rng.bit_generator.state, "sizes": list(self.sizes)}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        if list(sd["sizes"]) != list(self.sizes):
            raise ValueError(f"ES state of actors with {sd['sizes']} weights per role, these have {self.sizes}: "
                             "resume with the run's own config.toml")
        self.theta, self._m, self._v = (np.asarray(sd[k], dtype=np.float64).copy() for k in ("theta", "m", "v"))
        self.iteration = int(sd["iteration"])
        self.rng.bit_generator.state = sd["rng"]

    def team_actors(self) -> dict[int, Actor]:
        """Every team agent's actor at the current weights."""
        out: dict[int, Actor] = {}
        for r, t in zip(self.roles, self._split(self.theta[None])):
            actor = r.to_actor(t[0])
            for i in r.agents:
                out[i] = actor
        return out


def es_row(row: dict[str, Any]) -> list[str]:
    """A row of ``es.csv`` (``ES_COLUMNS``)."""
    return [f"{row[c]:.6g}" if isinstance(row[c], float) else str(row[c]) for c in ES_COLUMNS]
