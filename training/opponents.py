"""Opponent mixing (fictitious self-play) for the evaders during training.

With ``train.opponent_mix = f`` > 0, each env draws its evaders at every episode start: with probability
``1 - f`` the evaders are the learners (co-training, as in the paper), otherwise either a scripted evader from
``training.evader_suite.TrainingPool`` (behaviours and parameters drawn per env, disjoint from the held-out
evaluation suite; share ``train.opponent_scripted``) or a frozen snapshot of earlier learned evaders (taken
every ``train.opponent_snapshot_every`` env steps, the newest ``train.opponent_snapshots`` kept). The pursuer
team meets evaders it cannot overfit to; the learned evaders keep training in their own envs.

``train.evaders = "scripted"`` is the special case where every env runs ``training.baselines.FleeingEvaders``.

The mixer also says, per transition and agent, which next actions the trainer knows (``given``): a scripted
or frozen evader's next action is the one it really takes, so the critics must bootstrap on it rather than
on the learners' target actors (``training.maddpg``: the replay buffer's ``next_act``, NaN where the target
actors decide).
"""
from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch

from runtime.spec import SwarmSpec
from training.config import TrainConfig

LEARNED, SCRIPTED = -1, -2
"""Opponent codes per env; codes >= 0 index the snapshots."""


class OpponentMixer:
    """Chooses every env's evaders and produces their actions."""

    def __init__(self, spec: SwarmSpec, tc: TrainConfig, rng: np.random.Generator) -> None:
        self.spec = spec
        self.tc = tc
        self.nt = spec.team.n_team
        self.rng = rng
        self.kind = np.full(tc.n_envs, LEARNED, dtype=np.int64)
        self.snapshots: list[torch.nn.Module] = []
        self.scripted: Any = None
        self.pool: Any = None
        if tc.evaders == "scripted":
            from training.baselines import FleeingEvaders
            self.scripted = FleeingEvaders()
            self.kind[:] = SCRIPTED
        elif tc.opponent_mix > 0 and tc.opponent_scripted > 0:
            from training.evader_suite import TrainingPool
            self.pool = TrainingPool(seed=tc.seed + 11)

    @property
    def active(self) -> bool:
        return self.scripted is not None or self.tc.opponent_mix > 0

    def reset(self, env_ids: np.ndarray) -> None:
        """New episodes in ``env_ids``: draw their opponents."""
        tc = self.tc
        ids = np.asarray(env_ids, dtype=np.int64)
        if self.scripted is not None or tc.opponent_mix <= 0 or ids.size == 0:
            return
        mixed = self.rng.random(ids.size) < tc.opponent_mix
        scripted = mixed & (self.rng.random(ids.size) < tc.opponent_scripted)
        if self.pool is None:
            scripted[:] = False
        frozen = mixed & ~scripted
        kind = np.full(ids.size, LEARNED, dtype=np.int64)
        kind[scripted] = SCRIPTED
        if self.snapshots:
            kind[frozen] = self.rng.integers(0, len(self.snapshots), int(frozen.sum()))
        elif self.pool is not None:  # no snapshot yet: scripted instead
            kind[frozen] = SCRIPTED
        self.kind[ids] = kind
        drawn = ids[kind == SCRIPTED]
        if self.pool is not None and drawn.size:
            self.pool.resample(drawn)

    def snapshot_due(self, env_step: int) -> bool:
        """True every ``opponent_snapshot_every`` env steps while mixing with learned evaders."""
        tc = self.tc
        return tc.opponent_mix > 0 and self.scripted is None and env_step % tc.opponent_snapshot_every == 0

    def add_snapshot(self, actors: torch.nn.Module) -> None:
        """Freeze a copy of the actors (their evader rows are used), keeping the newest ``opponent_snapshots``."""
        tc = self.tc
        self.snapshots.append(copy.deepcopy(actors).requires_grad_(False))
        del self.snapshots[:-tc.opponent_snapshots]

    @torch.no_grad()
    def apply(self, obs: np.ndarray, actions: np.ndarray, env: Any, device: torch.device) -> np.ndarray:
        """Overwrite the evader columns of ``actions`` [B, N, 2] where an env's evaders are not the learners;
        returns ``given`` [B, N] (True where the action came from a scripted or frozen evader)."""
        given = np.zeros(actions.shape[:2], dtype=bool)
        nt = self.nt
        if self.scripted is not None:
            actions[:, nt:] = self.scripted.act(obs, env)[:, nt:]
            given[:, nt:] = True
            return given
        ids = np.nonzero(self.kind == SCRIPTED)[0]
        if self.pool is not None and ids.size:
            actions[ids, nt:] = self.pool.act(obs, env)[ids, nt:]
            given[ids, nt:] = True
        for k, snap in enumerate(self.snapshots):
            ids = np.nonzero(self.kind == k)[0]
            if ids.size == 0:
                continue
            o = torch.as_tensor(obs[ids], dtype=torch.float32, device=device).transpose(0, 1)
            a = snap(o).transpose(0, 1).cpu().numpy().astype(np.float64)  # [b, N, 2]
            actions[ids, nt:] = a[:, nt:]
            given[ids, nt:] = True
        return given

    def scripted_rows(self) -> np.ndarray:
        """[B, N] True where an agent's action comes from a scripted evader (no trained actor: the avoidance
        layer does not apply to it)."""
        rows = np.zeros((self.kind.size, self.spec.n_agents), dtype=bool)
        rows[self.kind == SCRIPTED, self.nt:] = True
        return rows

    def share(self) -> dict[str, float]:
        """Share of envs per opponent kind now."""
        n = self.kind.size
        return {"learned": float((self.kind == LEARNED).sum()) / n,
                "scripted": float((self.kind == SCRIPTED).sum()) / n,
                "snapshot": float((self.kind >= 0).sum()) / n}

    def state_dict(self) -> dict[str, Any]:
        return {"kind": self.kind.copy(), "snapshots": [s.state_dict() for s in self.snapshots]}

    def load_state_dict(self, sd: dict[str, Any], template: torch.nn.Module) -> None:
        self.kind = np.asarray(sd["kind"], dtype=np.int64).copy()
        self.snapshots = []
        for s in sd["snapshots"]:
            snap = copy.deepcopy(template).requires_grad_(False)
            snap.load_state_dict(s)
            self.snapshots.append(snap)
