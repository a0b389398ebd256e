"""Scripted evaders with randomized parameters: the held-out evaluation suite and a disjoint training pool.

Every behaviour follows the baselines' protocol (``training.baselines.Policy``)::

    actions = evaders.act(obs, env)      # [B, N, 2]; only the evader columns are set, team columns are zero

and reads the true world state from ``env.state`` (full information, like ``FleeingEvaders``). Each env draws
its own parameters (speeds, periods, margins, ...) from the behaviour's seeded generator at the start of every
episode: automatically when an env is at step 0 (a fresh or auto-reset env; ``act`` is called at every step,
as the evaluator and the trainer do), or on request with ``resample(env_ids)``. Draws happen only at episode
starts, so two evaluations with the same seed (the learned team's and the classical team's columns) meet
evaders with the same parameters, episode for episode.

Held-out suite (``SUITE``; ``swarm-train evaluate --evader suite`` or ``suite:KIND[,KIND]``), never trained
against:

- ``wanderer``: ignores the pursuers; visits random waypoints at a random speed.
- ``perimeter``: runs laps along the walls at a random inset and direction; turns back when a threat is ahead.
- ``hider``: keeps an obstacle between itself and the nearest threat; bolts when a threat gets close.
- ``juker``: flees the team (inverse-square weighted) in a zig-zag of random angle and period.
- ``predictive``: picks the heading whose predicted distance to the threats, after a random horizon in which
  every threat flies straight at it, is largest (a one-step look-ahead on time to capture).

Training pool (``POOL``, ``TrainingPool``), for opponent mixing: behaviours of other kinds, not only other
parameters, so that a team trained against the pool still meets the suite unseen. No class is in both
(``tests/test_evader_suite.py`` checks it), and neither contains ``FleeingEvaders``, the "scripted" evaluation
evaders.

- ``orbiter``: circles a random centre at a random radius and direction; ignores the pursuers.
- ``billiard``: flies straight and bounces off walls and obstacles.
- ``dodger``: drifts slowly until a threat is within a random trigger distance, then dashes sideways.
- ``nearest_fleer``: flees only the nearest threat, with a random reaction lag.
"""
from __future__ import annotations

import logging
import zlib
from typing import Any

import numpy as np

from training.baselines import avoid_obstacles, separation, wall_field

log = logging.getLogger(__name__)

__all__ = ["ScriptedEvaders", "SUITE", "POOL", "TrainingPool", "make_suite_evader", "parse_suite", "suite_seed"]


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.sqrt((v * v).sum(-1, keepdims=True))
    return v / np.maximum(n, 1e-9)


def _perp(v: np.ndarray) -> np.ndarray:
    return np.stack([-v[..., 1], v[..., 0]], axis=-1)


class ScriptedEvaders:
    """Base of every scripted evader here: per-env parameters drawn at episode starts, avoidance, the protocol.

    Subclasses set ``name`` and implement ``_draw(env, n)`` (a dict of arrays ``[n, E, ...]``: parameters and
    per-episode state) and ``_wish(env)`` (velocity wishes ``[B, E, 2]``, norm <= 1: the direction and the
    speed fraction before wall, obstacle and evader-evader avoidance)."""

    name = ""
    wall_reach = 0.5
    """Distance from a wall [m] where avoidance starts."""
    wall_repulsion = 1.0
    """Repulsion at a wall [normalized action]."""
    obstacle_reach = 0.3
    """Distance from an obstacle's surface [m] where avoidance starts."""
    obstacle_repulsion = 0.5
    """Repulsion at an obstacle's surface [normalized action]."""

    def __init__(self, seed: int | np.random.SeedSequence | None = None) -> None:
        self.rng = np.random.default_rng(seed)
        self.p: dict[str, np.ndarray] = {}
        self._pending = np.zeros(0, dtype=bool)
        self._at_start = np.zeros(0, dtype=bool)

    def resample(self, env_ids: Any) -> None:
        """Draw new parameters for ``env_ids`` on the next ``act`` (call it when those envs are reset)."""
        ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        self._pending[ids[ids < self._pending.size]] = True

    def act(self, obs: np.ndarray, env) -> np.ndarray:
        self._sync(env)
        nt = env.spec.team.n_team
        out = np.zeros(env.state.pos.shape[:2] + (2,))
        out[:, nt:] = self._steer(env, self._wish(env))
        return out

    # ---- parameters ---------------------------------------------------------------------------------
    def _sync(self, env) -> None:
        b = env.state.pos.shape[0]
        if self._pending.size != b:  # a new env (or batch size): every env starts over
            self._pending = np.ones(b, dtype=bool)
            self._at_start = np.zeros(b, dtype=bool)
            self.p = {}
        start = env.state.step == 0
        todo = np.nonzero(self._pending | (start & ~self._at_start))[0]
        self._at_start = start.copy()  # a second act at the same step 0 draws nothing new
        self._pending[:] = False
        if todo.size == 0:
            return
        new = self._draw(env, todo)
        for k, v in new.items():
            if k not in self.p:
                self.p[k] = np.zeros((b,) + v.shape[1:], dtype=v.dtype)
            self.p[k][todo] = v

    def _uniform(self, lo: float, hi: float, n: int, e: int) -> np.ndarray:
        return self.rng.uniform(lo, hi, (n, e))

    def _draw(self, env, ids: np.ndarray) -> dict[str, np.ndarray]:
        raise NotImplementedError

    def _wish(self, env) -> np.ndarray:
        raise NotImplementedError

    # ---- shared geometry ----------------------------------------------------------------------------
    @staticmethod
    def _evaders(env) -> tuple[np.ndarray, np.ndarray, int]:
        nt = env.spec.team.n_team
        return env.state.pos[:, nt:], env.state.pos[:, :nt], nt

    @staticmethod
    def _nearest_threat(ep: np.ndarray, tp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(position of each evader's nearest pursuer-team agent [B, E, 2], its distance [B, E])."""
        d = np.linalg.norm(ep[:, :, None] - tp[:, None], axis=-1)  # [B, E, T]
        j = d.argmin(-1)
        bi = np.arange(ep.shape[0])[:, None]
        return tp[bi, j], d[bi, np.arange(ep.shape[1])[None], j]

    def _steer(self, env, wish: np.ndarray) -> np.ndarray:
        """Wishes ``[B, E, 2]`` through evader-evader separation, walls and obstacles, keeping their speed."""
        spec, s = env.spec, env.state
        ep, _, nt = self._evaders(env)
        radius = np.asarray(spec.per_agent("radius"))[nt:]
        speed = np.minimum(np.linalg.norm(wish, axis=-1, keepdims=True), 1.0)
        v = wish + separation(ep, ep, 0.3, 1.5)
        v = wall_field(ep, v, radius, spec.arena.half_width, self.wall_reach, self.wall_repulsion)
        v = avoid_obstacles(ep, v, radius, s.obstacle_pos, s.obstacle_radius, self.obstacle_reach,
                            self.obstacle_repulsion)
        return _unit(v) * speed


# ================================================================================================ suite


class Wanderer(ScriptedEvaders):
    """Ignores the pursuers: flies to random waypoints (pushed out of obstacles) one after the other, moving
    on when within ``reach`` or after a random dwell time."""

    name = "wanderer"
    n_waypoints = 12

    def _draw(self, env, ids):
        n, e = ids.size, env.spec.team.n_evaders
        hw = env.spec.arena.half_width
        w = self.rng.uniform(-(hw - 0.3), hw - 0.3, (n, e, self.n_waypoints, 2))
        s = env.state
        for k in range(s.obstacle_pos.shape[1]):  # a waypoint inside an obstacle moves out to its surface
            c, r = s.obstacle_pos[ids, k][:, None, None], s.obstacle_radius[ids, k][:, None, None, None]
            d = w - c
            dist = np.linalg.norm(d, axis=-1, keepdims=True)
            w = np.where(dist < r + 0.25, c + _unit(d) * (r + 0.25), w)
        return {"waypoints": w, "speed": self._uniform(0.5, 1.0, n, e), "reach": self._uniform(0.1, 0.3, n, e),
                "dwell": self._uniform(15, 60, n, e), "index": np.zeros((n, e), dtype=np.int64),
                "since": np.zeros((n, e))}

    def _wish(self, env):
        ep, _, _ = self._evaders(env)
        p = self.p
        b, e = ep.shape[:2]
        bi, ei = np.arange(b)[:, None], np.arange(e)[None]
        step = env.state.step[:, None].astype(float)
        goal = p["waypoints"][bi, ei, p["index"]]
        done = (np.linalg.norm(goal - ep, axis=-1) < p["reach"]) | (step - p["since"] > p["dwell"])
        p["index"] = np.where(done, (p["index"] + 1) % self.n_waypoints, p["index"])
        p["since"] = np.where(done, step, p["since"])
        goal = p["waypoints"][bi, ei, p["index"]]
        return _unit(goal - ep) * p["speed"][..., None]


class PerimeterRunner(ScriptedEvaders):
    """Laps along the walls at a random inset, clockwise or not; turns back when the nearest threat is ahead
    on the track and closer than a random distance (then keeps the new direction for a random cooldown)."""

    name = "perimeter"
    wall_reach = 0.1
    wall_repulsion = 0.0

    def _draw(self, env, ids):
        n, e = ids.size, env.spec.team.n_evaders
        return {"inset": self._uniform(0.2, 0.6, n, e), "dir": self.rng.choice([-1.0, 1.0], (n, e)),
                "speed": self._uniform(0.7, 1.0, n, e), "turn_dist": self._uniform(0.5, 1.2, n, e),
                "cooldown": self._uniform(10, 30, n, e), "flipped": np.full((n, e), -1e9)}

    def _wish(self, env):
        ep, tp, _ = self._evaders(env)
        p = self.p
        L = env.spec.arena.half_width - p["inset"]  # [B, E]: the track is the square of half-side L
        x, y = ep[..., 0], ep[..., 1]
        vertical = np.abs(x) >= np.abs(y)  # nearest side is x = +-L
        proj = np.where(vertical[..., None],
                        np.stack([np.sign(x) * L, np.clip(y, -L, L)], -1),
                        np.stack([np.clip(x, -L, L), np.sign(y) * L], -1))
        # counter-clockwise tangents: +y on the right side, -y on the left, -x on top, +x at the bottom
        tangent = np.where(vertical[..., None], np.stack([np.zeros_like(x), np.sign(x)], -1),
                           np.stack([-np.sign(y), np.zeros_like(y)], -1))
        t = tangent * p["dir"][..., None]
        threat, dist = self._nearest_threat(ep, tp)
        ahead = ((threat - ep) * t).sum(-1) > 0
        step = env.state.step[:, None].astype(float)
        flip = ahead & (dist < p["turn_dist"]) & (step - p["flipped"] > p["cooldown"])
        p["dir"] = np.where(flip, -p["dir"], p["dir"])
        p["flipped"] = np.where(flip, step, p["flipped"])
        t = tangent * p["dir"][..., None]
        return _unit(t + 2.0 * (proj - ep)) * p["speed"][..., None]


class ObstacleHider(ScriptedEvaders):
    """Goes to the hiding spot behind an obstacle as seen from the nearest threat (the obstacle's far side at
    a random standoff), preferring spots near itself and far from the threat; flees the nearest threat
    directly when it is closer than a random panic distance, or when there are no obstacles."""

    name = "hider"

    def _draw(self, env, ids):
        n, e = ids.size, env.spec.team.n_evaders
        return {"standoff": self._uniform(0.1, 0.35, n, e), "panic": self._uniform(0.3, 0.7, n, e),
                "speed": self._uniform(0.7, 1.0, n, e)}

    def _wish(self, env):
        ep, tp, _ = self._evaders(env)
        s, p = env.state, self.p
        threat, dist = self._nearest_threat(ep, tp)
        flee = _unit(ep - threat)
        if s.obstacle_pos.shape[1] == 0:
            return flee * p["speed"][..., None]
        c = s.obstacle_pos[:, None]  # [B, 1, K, 2]
        r = s.obstacle_radius[:, None, :, None]
        hide = c + _unit(c - threat[:, :, None]) * (r + env.spec.evader.radius + p["standoff"][..., None, None])
        hw = env.spec.arena.half_width - 0.15
        hide = np.clip(hide, -hw, hw)
        cost = (np.linalg.norm(hide - ep[:, :, None], axis=-1)
                - 0.5 * np.linalg.norm(hide - threat[:, :, None], axis=-1))  # [B, E, K]
        k = cost.argmin(-1)
        b, e = ep.shape[:2]
        goal = hide[np.arange(b)[:, None], np.arange(e)[None], k]
        to_goal = goal - ep
        # at the spot: hold still (the distance factor), unless panicking
        go = _unit(to_goal) * np.minimum(1.0, np.linalg.norm(to_goal, axis=-1, keepdims=True) / 0.2)
        wish = np.where((dist < p["panic"])[..., None], flee, go)
        return wish * p["speed"][..., None]


def _flee_direction(ep: np.ndarray, tp: np.ndarray, softening: float = 0.2) -> np.ndarray:
    """Inverse-square weighted direction away from every threat ``[B, E, 2]`` (as ``FleeingEvaders``)."""
    d = ep[:, :, None] - tp[:, None]
    dist = np.sqrt((d * d).sum(-1))
    w = 1.0 / (dist + softening) ** 2
    return _unit(((w / np.maximum(dist, 1e-9))[..., None] * d).sum(2))


class Juker(ScriptedEvaders):
    """Flees the team in a zig-zag: the flee direction turned by +-``angle``, switching every ``period``
    steps (random angle, period and phase per evader)."""

    name = "juker"

    def _draw(self, env, ids):
        n, e = ids.size, env.spec.team.n_evaders
        period = self.rng.uniform(0.4, 1.6, (n, e)) / env.spec.timing.control_period
        return {"angle": np.radians(self._uniform(30, 70, n, e)), "period": period,
                "phase": self.rng.uniform(0, 1, (n, e)) * period, "speed": self._uniform(0.85, 1.0, n, e)}

    def _wish(self, env):
        ep, tp, _ = self._evaders(env)
        p = self.p
        f = _flee_direction(ep, tp)
        side = np.where(((env.state.step[:, None] + p["phase"]) // p["period"]) % 2 == 0, 1.0, -1.0)
        a = p["angle"] * side
        c, s = np.cos(a), np.sin(a)
        rot = np.stack([c * f[..., 0] - s * f[..., 1], s * f[..., 0] + c * f[..., 1]], -1)
        return rot * p["speed"][..., None]


class PredictiveFleer(ScriptedEvaders):
    """Tries ``n_headings`` headings; for each, predicts its own position after a random horizon at full
    speed and every threat's after flying straight at that position at its top speed, and takes the heading
    with the largest predicted distance to the nearest threat, less a penalty near walls and obstacles."""

    name = "predictive"
    n_headings = 16

    def _draw(self, env, ids):
        n, e = ids.size, env.spec.team.n_evaders
        return {"horizon": self._uniform(0.4, 1.2, n, e), "margin": self._uniform(0.3, 0.8, n, e),
                "offset": self.rng.uniform(0, 2 * np.pi / self.n_headings, (n, e)),
                "speed": self._uniform(0.85, 1.0, n, e)}

    def _wish(self, env):
        spec, s, p = env.spec, env.state, self.p
        ep, tp, nt = self._evaders(env)
        hw = spec.arena.half_width
        ang = p["offset"][..., None] + np.arange(self.n_headings) * (2 * np.pi / self.n_headings)  # [B, E, M]
        head = np.stack([np.cos(ang), np.sin(ang)], -1)
        reach = (spec.evader.max_speed * p["horizon"])[..., None, None]
        q = np.clip(ep[:, :, None] + head * reach, -hw, hw)  # [B, E, M, 2]
        vmax = np.asarray(spec.per_agent("max_speed"))[:nt]
        d = q[:, :, :, None] - tp[:, None, None]  # [B, E, M, T, 2] from threats to the predicted spot
        dist = np.linalg.norm(d, axis=-1)
        run = vmax * p["horizon"][..., None, None]
        # the gap left to the nearest threat once every threat has closed in; among spots where it is zero
        # ("caught anyway"), the small second term prefers the farthest
        score = np.maximum(dist - run, 0.0).min(-1) + 0.05 * dist.min(-1)
        wall = np.maximum(p["margin"][..., None, None] - (hw - np.abs(q)), 0.0).sum(-1)
        score = score - 2.0 * wall
        if s.obstacle_pos.shape[1]:
            od = np.linalg.norm(q[:, :, :, None] - s.obstacle_pos[:, None, None], axis=-1)
            inside = od - s.obstacle_radius[:, None, None] - p["margin"][..., None, None] * 0.5
            score = score - 2.0 * np.maximum(-inside, 0.0).sum(-1)
        best = score.argmax(-1)
        b, e = ep.shape[:2]
        return head[np.arange(b)[:, None], np.arange(e)[None], best] * p["speed"][..., None]


# ================================================================================================ pool


class Orbiter(ScriptedEvaders):
    """Circles a random centre at a random radius and direction; ignores the pursuers."""

    name = "orbiter"

    def _draw(self, env, ids):
        n, e = ids.size, env.spec.team.n_evaders
        hw = env.spec.arena.half_width
        return {"centre": self.rng.uniform(-0.4 * hw, 0.4 * hw, (n, e, 2)),
                "radius": self._uniform(0.4, 0.5 * hw, n, e), "dir": self.rng.choice([-1.0, 1.0], (n, e)),
                "speed": self._uniform(0.5, 1.0, n, e)}

    def _wish(self, env):
        ep, _, _ = self._evaders(env)
        p = self.p
        rel = ep - p["centre"]
        out = _unit(rel)
        err = (p["radius"] - np.linalg.norm(rel, axis=-1))[..., None]
        return _unit(_perp(out) * p["dir"][..., None] + 1.5 * err * out) * p["speed"][..., None]


class Billiard(ScriptedEvaders):
    """Flies straight at a random speed and bounces off walls and obstacles (mirror reflection)."""

    name = "billiard"
    wall_reach = 0.1
    wall_repulsion = 0.0

    def _draw(self, env, ids):
        n, e = ids.size, env.spec.team.n_evaders
        a = self.rng.uniform(0, 2 * np.pi, (n, e))
        return {"heading": np.stack([np.cos(a), np.sin(a)], -1), "speed": self._uniform(0.6, 1.0, n, e)}

    def _wish(self, env):
        spec, s = env.spec, env.state
        ep, _, _ = self._evaders(env)
        h = self.p["heading"]
        lim = spec.arena.half_width - spec.evader.radius - 0.1
        h = np.where((np.abs(ep) > lim) & (h * ep > 0), -h, h)
        for k in range(s.obstacle_pos.shape[1]):
            d = ep - s.obstacle_pos[:, None, k]
            n = _unit(d)
            near = np.linalg.norm(d, axis=-1) < s.obstacle_radius[:, None, k] + spec.evader.radius + 0.1
            into = (h * n).sum(-1)
            h = np.where((near & (into < 0))[..., None], h - 2 * into[..., None] * n, h)
        self.p["heading"] = h
        return h * self.p["speed"][..., None]


class Dodger(ScriptedEvaders):
    """Drifts slowly in a random direction until the nearest threat is within a random trigger distance, then
    dashes sideways to the threat's line (a random side), slightly away from it."""

    name = "dodger"

    def _draw(self, env, ids):
        n, e = ids.size, env.spec.team.n_evaders
        a = self.rng.uniform(0, 2 * np.pi, (n, e))
        return {"drift": np.stack([np.cos(a), np.sin(a)], -1) * self.rng.uniform(0.0, 0.25, (n, e, 1)),
                "trigger": self._uniform(0.6, 1.5, n, e), "side": self.rng.choice([-1.0, 1.0], (n, e))}

    def _wish(self, env):
        ep, tp, _ = self._evaders(env)
        p = self.p
        threat, dist = self._nearest_threat(ep, tp)
        away = _unit(ep - threat)
        dash = _unit(_perp(away) * p["side"][..., None] + 0.5 * away)
        return np.where((dist < p["trigger"])[..., None], dash, p["drift"])


class NearestFleer(ScriptedEvaders):
    """Flees only the nearest threat, its direction low-pass filtered with a random reaction time."""

    name = "nearest_fleer"

    def _draw(self, env, ids):
        n, e = ids.size, env.spec.team.n_evaders
        return {"tau": self._uniform(0.1, 0.6, n, e), "speed": self._uniform(0.6, 1.0, n, e),
                "dir": np.zeros((n, e, 2))}

    def _wish(self, env):
        ep, tp, _ = self._evaders(env)
        p = self.p
        threat, _ = self._nearest_threat(ep, tp)
        target = _unit(ep - threat)
        alpha = np.minimum(env.spec.timing.control_period / p["tau"], 1.0)[..., None]
        fresh = (np.linalg.norm(p["dir"], axis=-1, keepdims=True) < 1e-9)
        p["dir"] = np.where(fresh, target, p["dir"] + alpha * (target - p["dir"]))
        return _unit(p["dir"]) * p["speed"][..., None]


SUITE: dict[str, type[ScriptedEvaders]] = {c.name: c for c in (Wanderer, PerimeterRunner, ObstacleHider, Juker,
                                                                PredictiveFleer)}
"""The held-out evaluation suite, by kind."""
POOL: dict[str, type[ScriptedEvaders]] = {c.name: c for c in (Orbiter, Billiard, Dodger, NearestFleer)}
"""The training pool's behaviours, by kind (disjoint from ``SUITE``)."""


def suite_seed(seed: int, kind: str) -> np.random.SeedSequence:
    """The parameter generator's seed of one kind at evaluation seed ``seed`` (kinds draw independently)."""
    return np.random.SeedSequence([int(seed), zlib.crc32(kind.encode())])


def make_suite_evader(kind: str, seed: int = 0) -> ScriptedEvaders:
    """A held-out evader of ``kind`` (a key of ``SUITE``) whose parameters come from ``suite_seed``."""
    if kind not in SUITE:
        raise ValueError(f"unknown suite evader {kind!r}: use one of {list(SUITE)}")
    return SUITE[kind](suite_seed(seed, kind))


def parse_suite(spec: str) -> list[str]:
    """``"suite"`` -> every kind of ``SUITE``; ``"suite:wanderer,hider"`` -> those kinds."""
    if spec == "suite":
        return list(SUITE)
    if not spec.startswith("suite:"):
        raise ValueError(f"{spec!r} is not a suite selection: use 'suite' or 'suite:KIND[,KIND]'")
    kinds = [k.strip() for k in spec[len("suite:"):].split(",") if k.strip()]
    bad = [k for k in kinds if k not in SUITE]
    if bad or not kinds:
        raise ValueError(f"unknown suite kind {', '.join(bad) or '(none)'} in {spec!r}: use 'suite' or "
                         f"'suite:KIND[,KIND]' with KIND in {list(SUITE)}")
    return kinds


class TrainingPool:
    """Scripted training opponents: each env runs one behaviour of ``POOL`` (drawn uniformly, or by
    ``weights``) with its own parameters, redrawn with the behaviour by ``resample(env_ids)`` or when an env
    starts an episode (step 0). Only the evader columns of ``act`` are set.

    Disjoint from the held-out ``SUITE`` by construction: ``POOL`` and ``SUITE`` share no behaviour class, so
    evaluating against the suite meets behaviours, not only parameters, that training never saw."""

    def __init__(self, seed: int | None = None, kinds: list[str] | None = None,
                 weights: list[float] | None = None) -> None:
        self.kinds = list(kinds or POOL)
        bad = [k for k in self.kinds if k not in POOL]
        if bad:
            raise ValueError(f"unknown training pool kind {bad}: use kinds from {list(POOL)}")
        w = np.ones(len(self.kinds)) if weights is None else np.asarray(weights, dtype=float)
        if w.shape != (len(self.kinds),) or (w < 0).any() or w.sum() <= 0:
            raise ValueError(f"weights must be {len(self.kinds)} non-negative numbers, not all zero; got {weights}")
        self.weights = w / w.sum()
        ss = np.random.SeedSequence(seed)
        self.rng = np.random.default_rng(ss.spawn(1)[0])
        self.behaviours = [POOL[k](child) for k, child in zip(self.kinds, ss.spawn(len(self.kinds)))]
        self.choice = np.zeros(0, dtype=np.int64)
        """[B] the index in ``kinds`` each env runs."""
        self._at_start = np.zeros(0, dtype=bool)

    def resample(self, env_ids: Any) -> None:
        """New behaviour and parameters for ``env_ids`` (call on their episode reset)."""
        ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        ids = ids[ids < self.choice.size]
        self.choice[ids] = self.rng.choice(len(self.kinds), ids.size, p=self.weights)
        for beh in self.behaviours:
            beh.resample(ids)
        self._at_start[ids] = True  # the act at their step 0 must not draw a second time

    def act(self, obs: np.ndarray, env) -> np.ndarray:
        b = env.state.pos.shape[0]
        if self.choice.size != b:
            self.choice = self.rng.choice(len(self.kinds), b, p=self.weights)
            self._at_start = np.ones(b, dtype=bool)
        start = env.state.step == 0
        new = np.nonzero(start & ~self._at_start)[0]
        if new.size:
            self.choice[new] = self.rng.choice(len(self.kinds), new.size, p=self.weights)
        self._at_start = start.copy()
        out = np.zeros(env.state.pos.shape[:2] + (2,))
        for i, beh in enumerate(self.behaviours):
            a = beh.act(obs, env)  # every behaviour steps every env so that its per-env state stays current
            rows = self.choice == i
            out[rows] = a[rows]
        return out

    def counts(self) -> dict[str, int]:
        """How many envs run each behaviour now."""
        return {k: int((self.choice == i).sum()) for i, k in enumerate(self.kinds)}
