"""An evader of your own, evaluated with ``--evader examples/evaders/gap_runner.py:GapRunner``.

``GapRunner`` runs for the widest gap in the ring of threats around it: it takes the bearings of the pursuer-team
agents within its awareness radius (and of the nearest point of each wall within its wall radius, as if a threat
stood there), finds the largest angle between two neighbouring bearings and flies along that angle's bisector.
With no threat in sight it drifts slowly towards a spot of its own. It breaks out between two pursuers where a
fleer (which flees the weighted sum of the threats) runs into the corner they leave open.

It was written on 2026-12-08, after every recipe in results/README.md had been chosen, so no choice of training
setting, teacher or ES length ever saw it: the one opponent here that is held out from the choices as well as from
training (the suite's five kinds were held out from training, but the later attempts chose on them). It is not in
the training pool (``training.evader_suite.POOL``) either.

How to write your own: subclass ``training.evader_suite.ScriptedEvaders`` (per-episode parameters drawn from the
seed, so that the learned team and the classical team meet the same evaders; walls, obstacles and evader-evader
separation handled for you) and implement ``_draw`` and ``_wish``; or write any class with ``act(obs, env)``
returning ``[B, N, 2]`` actions (only the evader columns are used), built as ``Class(seed=S)`` or ``Class()``.

    swarm-train evaluate --models models/role_based --evader examples/evaders/gap_runner.py:GapRunner \\
        --episodes 200 --seed 0
"""
from __future__ import annotations

import numpy as np

from training.evader_suite import ScriptedEvaders


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.sqrt((v * v).sum(-1, keepdims=True))
    return v / np.maximum(n, 1e-9)


def widest_gap(bearings: np.ndarray, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bisector [rad] and the width [rad] of the largest angle between neighbouring ``bearings`` ``[..., K]``
    among those ``active`` (one active bearing: the gap is the whole circle, its bisector straight opposite).
    Rows with none active give width 0 and bisector 0."""
    two_pi = 2.0 * np.pi
    a = np.sort(np.where(active, np.mod(bearings, two_pi), 4.0 * two_pi), axis=-1)  # inactive ones sort last
    k = active.sum(-1)  # [...]
    first = a[..., :1]
    nxt = np.concatenate([a[..., 1:], first], axis=-1)
    idx = np.arange(a.shape[-1])
    last = idx == (k[..., None] - 1)
    nxt = np.where(last, first + two_pi, nxt)  # the wrap-around gap closes the ring
    gap = np.where(idx < k[..., None], nxt - a, -1.0)
    best = gap.argmax(-1)[..., None]
    width = np.take_along_axis(gap, best, -1)[..., 0]
    mid = np.take_along_axis(a, best, -1)[..., 0] + 0.5 * width
    none = k == 0
    return np.where(none, 0.0, np.mod(mid, two_pi)), np.where(none, 0.0, width)


class GapRunner(ScriptedEvaders):
    """Runs along the bisector of the widest gap between the threats (and the walls) around it.

    Drawn per evader and episode: the awareness radius (1.2-3 m), the wall radius (0.4-0.9 m), the speed
    (0.85-1 of the top speed), the idle drift's speed (0.2-0.5) and spot."""

    name = "gap_runner"

    def _draw(self, env, ids):
        n, e = ids.size, env.spec.team.n_evaders
        hw = env.spec.arena.half_width
        return {"aware": self._uniform(1.2, 3.0, n, e), "wall": self._uniform(0.4, 0.9, n, e),
                "speed": self._uniform(0.85, 1.0, n, e), "idle": self._uniform(0.2, 0.5, n, e),
                "spot": self.rng.uniform(-0.6 * hw, 0.6 * hw, (n, e, 2))}

    def _wish(self, env):
        p = self.p
        ep, tp, _ = self._evaders(env)  # [B, E, 2], [B, T, 2]
        hw = env.spec.arena.half_width
        rel = tp[:, None] - ep[:, :, None]  # [B, E, T, 2] from the evader to each threat
        seen = np.linalg.norm(rel, axis=-1) < p["aware"][..., None]
        # from the evader to each wall's nearest point: +x, -x, +y, -y
        x, y, zero = ep[..., 0], ep[..., 1], np.zeros_like(ep[..., 0])
        walls = np.stack([np.stack(w, -1) for w in ((hw - x, zero), (-hw - x, zero), (zero, hw - y), (zero, -hw - y))],
                         axis=2)  # [B, E, 4, 2]
        near_wall = np.abs(walls).sum(-1) < p["wall"][..., None]
        rel = np.concatenate([rel, walls], axis=2)
        active = np.concatenate([seen, near_wall], axis=2)
        mid, _ = widest_gap(np.arctan2(rel[..., 1], rel[..., 0]), active)
        run = np.stack([np.cos(mid), np.sin(mid)], -1) * p["speed"][..., None]
        drift = _unit(p["spot"] - ep) * p["idle"][..., None]
        return np.where(seen.any(-1, keepdims=True), run, drift)
