"""Opponent mixing and the next actions it stores: scripted and frozen evaders' real next actions reach the
replay buffer (finite), the learners' stay NaN (their target actors decide), and the TD target uses them."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from runtime.spec import SpecError
from training.config import ExperimentConfig, TrainConfig
from training.opponents import LEARNED, SCRIPTED
from training.train import Trainer

TEAM = {"n_pursuers": 2, "n_scouts": 0, "n_evaders": 1}


def _cfg(**train) -> ExperimentConfig:
    tc = dict(n_envs=4, batch_size=32, buffer_size=5000, warmup_steps=5, noise_decay_steps=50, log_every=25,
              checkpoint_every=1000, threads=1, steps=60)
    tc.update(train)
    return ExperimentConfig.from_dict({"name": "mix", "spec": {"team": TEAM}, "train": tc})


def _buffer(trainer: Trainer) -> dict[str, np.ndarray]:
    n = len(trainer.buffer)
    return {k: getattr(trainer.buffer, k)[:n].numpy() for k in ("obs", "act", "next_obs", "next_act")}


def test_scripted_evaders_store_the_next_action_they_take(tmp_path):
    trainer = Trainer(_cfg(evaders="scripted", steps=30), tmp_path / "run")
    trainer.run(progress=False)
    b = _buffer(trainer)
    n_envs = 4
    assert len(trainer.buffer) == 30 * n_envs
    assert np.isnan(b["next_act"][:, :2]).all()  # pursuers learn: their target actors decide
    ev_next = b["next_act"][:, 2]
    assert np.isfinite(ev_next).all()
    # transition t+1's action of the evader is transition t's next action (no episode ends in 30 steps)
    assert np.allclose(ev_next[:-n_envs], b["act"][n_envs:, 2], atol=1e-6)


def test_mixed_envs_give_scripted_and_frozen_evaders_next_actions(tmp_path):
    trainer = Trainer(_cfg(opponent_mix=1.0, opponent_scripted=0.5, opponent_snapshot_every=10,
                           opponent_snapshots=2, steps=120), tmp_path / "run")
    seen = set()
    orig = trainer.mixer.reset

    def spy(ids):
        orig(ids)
        seen.update(int(k) for k in trainer.mixer.kind[np.asarray(ids)])
    trainer.mixer.reset = spy
    trainer.run(progress=False)
    assert len(trainer.mixer.snapshots) == 2  # the newest two of twelve
    assert SCRIPTED in seen and any(k >= 0 for k in seen) and LEARNED not in seen  # mix = 1: never the learners
    b = _buffer(trainer)
    assert np.isfinite(b["next_act"][:, 2]).all() and np.isnan(b["next_act"][:, :2]).all()


def test_no_mixing_stores_nan_for_every_learner(tmp_path):
    trainer = Trainer(_cfg(steps=20), tmp_path / "run")
    trainer.run(progress=False)
    assert np.isnan(_buffer(trainer)["next_act"]).all()
    assert trainer.mixer.share() == {"learned": 1.0, "scripted": 0.0, "snapshot": 0.0}


def test_td_target_bootstraps_on_a_given_action_of_a_learner(tmp_path):
    trainer = Trainer(_cfg(steps=10), tmp_path / "run")
    agent = trainer.agent
    k, n, d = 8, agent.n_agents, agent.obs_dim
    g = torch.Generator().manual_seed(0)
    next_obs = torch.rand(k, n, d, generator=g)
    given = torch.full((k, n, 2), float("nan"))
    given[:, 2] = 0.7  # the evader learns, but was frozen in these envs: it really took 0.7
    acts = agent.target_next_actions(next_obs, given)
    tgt = agent.actors_tgt(next_obs.transpose(0, 1)).transpose(0, 1)
    assert torch.allclose(acts[:, 2], torch.full((k, 2), 0.7))
    assert torch.allclose(acts[:, :2], tgt[:, :2])
    assert torch.allclose(agent.target_next_actions(next_obs, None), tgt)


def test_mixing_resumes_with_its_snapshots(tmp_path):
    cfg = _cfg(opponent_mix=0.5, opponent_snapshot_every=10, steps=30)
    Trainer(cfg, tmp_path / "run").run(progress=False)
    more = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=40))
    again = Trainer(more, tmp_path / "run", resume=True)
    assert len(again.mixer.snapshots) == 3
    again.run(progress=False)
    assert len(again.mixer.snapshots) == 4


@pytest.mark.parametrize("field, value, fix", [("opponent_mix", 1.5, r"\[0, 1\]"),
                                               ("opponent_snapshots", 0, ">= 1")])
def test_bad_mixing_options_name_the_field(field, value, fix):
    with pytest.raises(SpecError, match=f"train.{field}.*{fix}"):
        dataclasses.replace(TrainConfig(), **{field: value})


def test_mixing_needs_learned_evaders():
    with pytest.raises(SpecError, match="train.opponent_mix.*train.evaders = 'learned'"):
        TrainConfig(opponent_mix=0.5, evaders="scripted")
