"""Learner updates per second, role_based (5 pursuers, 5 scouts, 2 evaders: 12 agents, 45-float observations),
batch 256, one torch thread: the learner options of issue 13 side by side in one run.

- ``before``: the default learner with the critics' shared input multiplied as before (one batched matmul
  over 12 broadcast copies; ``training.networks.shared_matmul`` replaced by ``torch.matmul``);
- ``default``: today's default (the paper's MADDPG; bitwise the same updates as ``before``);
- ``global``, ``share_global``, ``matd3``, ``share_global_matd3``: the options (``train.critic = "global"``,
  ``train.share_params``, ``train.algorithm = "matd3"``).

Target (issue 13): a fast option >= 3x the 53 updates/s measured before it on an idle core.

Run: .venv/bin/python -m pytest tests/benchmarks/test_bench_maddpg.py --benchmark-enable
"""
import dataclasses

import numpy as np
import pytest
import torch

from training import networks
from training.config import ExperimentConfig
from training.maddpg import MADDPG

VARIANTS = {
    "before": {},
    "default": {},
    "global": {"critic": "global"},
    "share_global": {"share_params": True, "critic": "global"},
    "matd3": {"algorithm": "matd3"},
    "share_global_matd3": {"share_params": True, "critic": "global", "algorithm": "matd3"},
}


@pytest.fixture
def one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.mark.benchmark(group="maddpg_update_role_based_batch256")
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_update(benchmark, variant, one_thread, monkeypatch):
    if variant == "before":
        monkeypatch.setattr(networks, "shared_matmul", torch.matmul)
    cfg = ExperimentConfig.from_dict({"name": "bench", "spec": {"team": {"n_pursuers": 5, "n_scouts": 5,
                                                                         "n_evaders": 2}}})
    tc = dataclasses.replace(cfg.train, batch_size=256, threads=1, **VARIANTS[variant])
    agent = MADDPG(cfg.spec, tc)
    n, d, k = cfg.spec.n_agents, cfg.spec.max_obs_dim, tc.batch_size
    g = torch.Generator().manual_seed(0)
    batch = (torch.randn(k, n, d, generator=g), torch.rand(k, n, 2, generator=g) * 2 - 1,
             torch.randn(k, n, generator=g), torch.randn(k, n, d, generator=g), torch.full((k, n, 2), float("nan")))
    for _ in range(3):  # allocator and optimizer state warm
        agent.update(batch)
    losses = benchmark(agent.update, batch)
    assert np.isfinite(losses["critic_loss"])
    if benchmark.stats:
        benchmark.extra_info["updates_per_s_median"] = 1.0 / benchmark.stats.stats.median
        benchmark.extra_info["updates_per_s_best"] = 1.0 / benchmark.stats.stats.min
