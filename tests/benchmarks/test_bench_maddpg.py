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
- ``shipped_unpooled``: ``shipped`` without the reused activation buffers (``training.networks._PooledMLP``) and
  the flat parameters (``training.maddpg.FlatAdam``): per-tensor fused Adam, every layer through ``shared_linear``
  (the same values bit for bit);
- ``shipped_c128``: the same with the 128-128 critics it shipped with until then.

Target (issue 13): a fast option >= 3x ``before``.

Run: .venv/bin/python -m pytest tests/benchmarks/test_bench_maddpg.py --benchmark-enable
(each variant's rounds one after the other), or interleaved: every variant once per round in a new random order, a
ratio to ``before`` per round (a busy stretch of a shared machine slows every variant of that round alike):
.venv/bin/python tests/benchmarks/test_bench_maddpg.py --rounds 300 [--json FILE]
"""
import argparse
import contextlib
import dataclasses
import json
import random
import time
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
}
SHIPPED = {"shipped": {}, "shipped_unpooled": {}, "shipped_c128": {"critic_hidden": (128, 128)}}
"""Variants on configs/role_based.toml's learner settings (the rows above: on the default config's)."""
ALL = [*VARIANTS, *SHIPPED]


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


def _old_adam(online, lr, target=None):
    return torch.optim.Adam(online.parameters(), lr=lr)


def _old_forward_pre(self, x, index=None, in_scale=None, in_shift=None):
    assert in_scale is None  # the `before` row: no input scaling (the default config)
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


def _unflat_adam(online, lr, target=None):
    return torch.optim.Adam(online.parameters(), lr=lr, fused=True)


@contextlib.contextmanager
def _patched(variant: str):
    """While the block runs, the learner's helpers as they were when issue 13 was filed (the ``before`` row), or
    without this session's buffers and flat parameters (``shipped_unpooled``); Adam is chosen when a learner is
    built, the rest at every call."""
    patches = {"before": [(networks, "shared_matmul", torch.matmul), (maddpg, "soft_update", _old_soft_update),
                          (maddpg, "clip_grad_norm_per_agent", _old_clip), (maddpg, "adam", _old_adam),
                          (networks.BatchedMLP, "forward_pre", _old_forward_pre)],
               "shipped_unpooled": [(networks, "POOLED", False), (maddpg, "adam", _unflat_adam)]}.get(variant, [])
    saved = [(obj, name, getattr(obj, name)) for obj, name, _ in patches]
    for obj, name, new in patches:
        setattr(obj, name, new)
    try:
        yield
    finally:
        for obj, name, old in saved:
            setattr(obj, name, old)


def _learner(variant: str):
    """(learner, batch) of a variant, warmed by 3 updates; build and call it inside ``_patched(variant)``."""
    if variant in SHIPPED:
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
    return agent, batch


@pytest.mark.benchmark(group="maddpg_update_role_based_batch256")
@pytest.mark.parametrize("variant", ALL)
def test_update(benchmark, variant, one_thread):
    with _patched(variant):
        agent, batch = _learner(variant)
        losses = benchmark(agent.update, batch)
    assert np.isfinite(losses["critic_loss"])
    if benchmark.stats:
        benchmark.extra_info["updates_per_s_median"] = 1.0 / benchmark.stats.stats.median
        benchmark.extra_info["updates_per_s_best"] = 1.0 / benchmark.stats.stats.min


def interleaved(rounds: int, seed: int = 0, block: int = 1) -> dict:
    """Every variant's update timed once per round, the variants in a new random order each round, so that a
    stretch of a busy machine slows all of them alike: per variant the median time and the median over rounds of
    ``before``'s time in that round over the variant's (a paired ratio). ``block`` > 1: each variant runs that
    many updates back to back per round (as a training does, its memory and caches its own) and the round's
    time is their median."""
    torch.set_num_threads(1)
    made = {}
    for v in ALL:
        with _patched(v):
            made[v] = _learner(v)
    order = list(ALL)
    rng = random.Random(seed)
    times: dict[str, list[float]] = {v: [] for v in ALL}
    for _ in range(rounds):
        rng.shuffle(order)
        for v in order:
            agent, batch = made[v]
            with _patched(v):
                ts = []
                for _ in range(block):
                    t0 = time.perf_counter()
                    agent.update(batch)
                    ts.append(time.perf_counter() - t0)
                times[v].append(float(np.median(ts)))
    before = np.array(times["before"])
    out = {}
    for v, t in times.items():
        ms, ratio = 1e3 * np.percentile(t, [25, 50, 75]), np.percentile(before / np.array(t), [25, 50, 75])
        out[v] = {"median_ms": float(ms[1]), "p25_ms": float(ms[0]), "p75_ms": float(ms[2]),
                  "ratio_to_before_median": float(ratio[1]), "ratio_to_before_p25": float(ratio[0]),
                  "ratio_to_before_p75": float(ratio[2])}
    return {"rounds": rounds, "block": block, "variants": out}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description="Learner updates interleaved: every variant once per round, in a new "
                                 "random order each round; per variant the median time and the median paired "
                                 "ratio to the `before` learner of the same round.")
    ap.add_argument("--rounds", type=int, default=300, help="rounds (each times every variant once)")
    ap.add_argument("--block", type=int, default=1, help="updates of a variant back to back per round (the "
                    "round's time: their median)")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    ap.add_argument("--profile", metavar="VARIANT", choices=ALL,
                    help="instead: this variant's time and minor page faults per update, and torch.profiler's "
                    "table of 10 updates, by self CPU time (ROWS=N in the environment: N rows, default 15)")
    args = ap.parse_args()
    if args.profile:
        import resource

        from torch.profiler import ProfilerActivity, profile
        torch.set_num_threads(1)
        with _patched(args.profile):
            agent, batch = _learner(args.profile)
            for _ in range(30):
                agent.update(batch)
            faults, t0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.perf_counter()
            for _ in range(100):
                agent.update(batch)
            print(f"{args.profile}: {10 * (time.perf_counter() - t0):.2f} ms per update, "
                  f"{(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults) / 100:.1f} minor page faults per "
                  "update (100 updates after 30, back to back)")
            with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
                for _ in range(10):
                    agent.update(batch)
        print(prof.key_averages(group_by_input_shape=True).table(sort_by="self_cpu_time_total", row_limit=int(__import__("os").environ.get("ROWS", 15)),
                                                                 max_name_column_width=30))
        raise SystemExit(0)
    out = interleaved(args.rounds, block=args.block)
    print(f"{'variant':14s} {'median ms':>10s} {'p25-p75 ms':>14s} {'x before (paired median, p25-p75)':>36s}")
    for v, r in out["variants"].items():
        print(f"{v:14s} {r['median_ms']:10.2f} {r['p25_ms']:6.2f}-{r['p75_ms']:<7.2f} "
              f"{r['ratio_to_before_median']:>20.2f} ({r['ratio_to_before_p25']:.2f}-{r['ratio_to_before_p75']:.2f})")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
