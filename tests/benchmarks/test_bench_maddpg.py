"""Learner updates per second, role_based (5 pursuers, 5 scouts, 2 evaders: 12 agents, 45-float observations),
batch 256, one torch thread: the learner as it was when issue 13 was filed and its options, side by side in one
run.

- ``before``: the default learner (the paper's MADDPG) exactly as it was measured at 53 updates/s when issue 13
  was filed: per-tensor Adam, per-tensor soft updates and gradient scaling, and the critics' shared input
  multiplied as a batched matmul over 12 broadcast copies, and every layer as a batched matmul then a bias add
  (the old functions are restored below for this row only);
- ``default``: today's default learner (the same algorithm; fused Adam, fused soft updates and gradient
  scaling, one GEMM for the critics' shared input, ``training.networks.shared_linear``'s layers);
- ``global``: ``train.critic = "global"`` (one critic per agent on the compact global state);
- ``role``, ``role_share``: ``train.critic = "role"`` (one critic per role with a head per agent,
  ``training.rolecritic``), without and with ``train.share_params``;
- ``shipped``: the learner settings of configs/role_based.toml (64-64 role critics since issue 13's eighth attempt);
- ``shipped_c128``: the same with the 128-128 critics it shipped with until then.

Target (issue 13): a fast option >= 3x ``before``.

Run: .venv/bin/python -m pytest tests/benchmarks/test_bench_maddpg.py --benchmark-enable
"""
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from training import maddpg, networks
from training.config import ExperimentConfig
from training.rolecritic import make_learner

ROOT = Path(__file__).resolve().parents[2]
VARIANTS = {
    "before": {},
    "default": {},
    "global": {"critic": "global"},
    "role": {"critic": "role"},
    "role_share": {"critic": "role", "share_params": True},
    "shipped": None,
    "shipped_c128": None,
}
SHIPPED = {"shipped": {}, "shipped_c128": {"critic_hidden": (128, 128)}}


# ---- the learner's helpers as they were when issue 13 was filed (the `before` row) -------------------------
def _old_soft_update(target, online, tau):
    for t, o in zip(target.parameters(), online.parameters()):
        t.lerp_(o, tau)


def _old_clip(params, max_norm):
    grads = [p.grad for p in params if p.grad is not None]
    sq = torch.stack([g.pow(2).reshape(g.shape[0], -1).sum(1) for g in grads]).sum(0)
    norms = sq.sqrt()
    if max_norm > 0:
        scale = (max_norm / (norms + 1e-6)).clamp(max=1.0)
        for g in grads:
            g.mul_(scale.view(-1, *([1] * (g.dim() - 1))))
    return norms


def _old_adam(params, lr):
    return torch.optim.Adam(params, lr=lr)


def _old_forward_pre(self, x, index=None):
    layers = self.layers(index)
    for k, (w, b) in enumerate(layers):
        x = torch.matmul(x, w) + b
        if k < len(layers) - 1:
            x = torch.relu(x)
    return x


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
        monkeypatch.setattr(maddpg, "soft_update", _old_soft_update)
        monkeypatch.setattr(maddpg, "clip_grad_norm_per_agent", _old_clip)
        monkeypatch.setattr(maddpg, "adam", _old_adam)
        monkeypatch.setattr(networks.BatchedMLP, "forward_pre", _old_forward_pre)
    if VARIANTS[variant] is None:
        shipped = ExperimentConfig.from_toml(ROOT / "configs" / "role_based.toml")
        spec, tc = shipped.spec, dataclasses.replace(shipped.train, threads=1, **SHIPPED[variant])
    else:
        cfg = ExperimentConfig.from_dict({"name": "bench", "spec": {"team": {"n_pursuers": 5, "n_scouts": 5,
                                                                             "n_evaders": 2}}})
        spec, tc = cfg.spec, dataclasses.replace(cfg.train, batch_size=256, threads=1, **VARIANTS[variant])
    assert tc.batch_size == 256 and spec.n_agents == 12
    agent = make_learner(spec, tc)
    n, d, k = spec.n_agents, spec.max_obs_dim, tc.batch_size
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
