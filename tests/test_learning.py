"""The learning check: with a fixed seed, a short MADDPG run on the smallest setting (one pursuer, one
target that holds still, no scouts) beats the random policy by a clear margin on held-out episodes."""
from __future__ import annotations

import numpy as np

from training.baselines import RandomPolicy
from training.config import ExperimentConfig
from training.evaluate import evaluate
from training.learned_eval import load_learned
from training.train import Trainer


class _StillTargets:
    """The pursuer's action from ``policy``; the target holds still (as during training)."""

    def __init__(self, policy) -> None:
        self.policy = policy

    def act(self, obs: np.ndarray, env) -> np.ndarray:
        a = np.array(self.policy.act(obs, env), dtype=np.float64)
        a[:, 1:] = 0.0
        return a


def test_one_pursuer_learns_to_reach_a_static_target(tmp_path):
    cfg = ExperimentConfig.from_dict({
        "name": "one_vs_static",
        "spec": {"team": {"n_pursuers": 1, "n_scouts": 0, "n_evaders": 1}},
        "train": {"steps": 800, "n_envs": 16, "seed": 0, "batch_size": 128, "warmup_steps": 50,
                  "noise_decay_steps": 400, "evaders": "static", "threads": 1, "log_every": 100,
                  "checkpoint_every": 100000, "checkpoint_buffer": False}})
    result = Trainer(cfg, tmp_path / "run").run(progress=False)
    assert result.env_steps == 800 and result.updates > 700
    _, learned, _ = load_learned(run=tmp_path / "run")
    ours = evaluate(cfg, _StillTargets(learned), 40, seed=0, n_envs=20, progress=False)
    rand = evaluate(cfg, _StillTargets(RandomPolicy(0)), 40, seed=0, n_envs=20, progress=False)
    # the random pursuer wanders ~2 m from the target; the trained one closes in and stays near it
    assert ours["mean_min_dist"] < 0.5 * rand["mean_min_dist"], (ours["mean_min_dist"], rand["mean_min_dist"])
    assert ours["mean_avg_dist"] < 0.6 * rand["mean_avg_dist"], (ours["mean_avg_dist"], rand["mean_avg_dist"])
