"""Evaluation of any ``training.baselines.Policy`` on the paper's metrics, and the comparison table.

Seed scheme: evaluation never meets a training seed. Round ``r`` (a batch of up to ``n_envs`` episodes) of
``evaluate(..., seed=S)`` runs a fresh ``PursuitEnv`` seeded with ``numpy.random.SeedSequence([EVAL_SEED_OFFSET
+ S, r])``; training seeds are plain integers below ``EVAL_SEED_OFFSET`` fed to ``default_rng``, whose streams
differ from those of a two-word entropy. The same ``(cfg, policy, episodes, seed, n_envs)`` gives the same
numbers (the episodes' starts depend on ``n_envs`` too, since a round's envs share one generator).
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from tqdm import tqdm

from runtime.metrics import METRIC_KEYS, summarize
from runtime.paper import PAPER  # noqa: F401  (re-exported: the paper's figures, defined once in runtime)
from training.baselines import Policy
from training.config import ExperimentConfig
from training.env import PursuitEnv

log = logging.getLogger(__name__)

EVAL_SEED_OFFSET = 10 ** 6
"""Added to the evaluation seed; training seeds stay below it."""

_LABELS = {
    "episodes": "episodes",
    "mean_min_dist": "min pursuer-target distance [m]",
    "mean_avg_dist": "mean pursuer-target distance [m]",
    "mean_max_dist": "max pursuer-target distance [m]",
    "tracking_rate": "tracking rate (target within 0.5 m)",
    "coverage": "coverage (episode)",
    "coverage_instant": "coverage (instantaneous)",
    "collisions_per_episode": "collisions / episode (all)",
    "team_contacts_per_episode": "  team's own (teammate + obstacle)",
    "teammate_contacts_per_episode": "  teammate contacts / episode",
    "team_obstacle_contacts_per_episode": "  team-obstacle contacts / episode",
    "evader_contacts_per_episode": "  evader-side contacts / episode",
    "captures_per_episode": "captures / episode",
}


def eval_seed(seed: int, round_index: int) -> np.random.SeedSequence:
    """The world seed of one evaluation round (see the module docstring)."""
    return np.random.SeedSequence([EVAL_SEED_OFFSET + int(seed), int(round_index)])


def evaluate(cfg: ExperimentConfig, policy: Policy, episodes: int, seed: int = 0, n_envs: int = 50,
             progress: bool = True, desc: str | None = None, records_out: list | None = None) -> dict[str, float]:
    """Runs exactly ``episodes`` episodes of ``policy`` in ``cfg``'s world and returns ``summarize``'s dict
    (keys ``runtime.metrics.METRIC_KEYS``) plus ``wall_s``, the seconds it took. ``records_out``: a list that
    receives every episode's ``runtime.metrics.EpisodeRecord``, in episode order (the same order for every policy
    evaluated with the same ``seed``, ``episodes`` and ``n_envs``: the episodes are paired)."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if n_envs < 1:
        raise ValueError(f"n_envs must be >= 1, got {n_envs}")
    steps = cfg.spec.timing.episode_steps
    rounds = math.ceil(episodes / n_envs)
    records = []
    t0 = time.perf_counter()
    bar = tqdm(total=episodes, desc=desc or f"evaluate {cfg.name}", unit="ep", disable=not progress, leave=False)
    for r in range(rounds):
        b = min(n_envs, episodes - r * n_envs)
        env = PursuitEnv(cfg.spec, cfg.rewards, n_envs=b, seed=eval_seed(seed, r), track_metrics=True)
        obs = env.reset()
        for _ in range(steps):
            obs, _, done, info = env.step(policy.act(obs, env))
        if not done.all():
            raise RuntimeError("episodes did not end together after spec.timing.episode_steps steps")
        records += info["episodes"]
        bar.update(b)
    bar.close()
    if records_out is not None:
        records_out.extend(records)
    out: dict[str, float] = summarize(records)
    out["wall_s"] = time.perf_counter() - t0
    log.info("evaluated %d episodes of %s in %.1f s", len(records), cfg.name, out["wall_s"])
    return out


def mean_of(docs: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """The mean of several evaluations' metrics (e.g. over the kinds of the evader suite): every metric of
    ``METRIC_KEYS`` averaged with equal weight per evaluation; ``episodes`` and ``wall_s`` summed."""
    out: dict[str, float] = {}
    for k in METRIC_KEYS:
        vals = [d[k] for d in docs if k in d]
        if vals and k != "episodes":
            out[k] = float(np.mean(vals))
    out["episodes"] = int(sum(d.get("episodes", 0) for d in docs))
    out["wall_s"] = float(sum(d.get("wall_s", 0.0) for d in docs))
    return out


from runtime.cliutil import write_text_atomic  # noqa: E402,F401  (one atomic write for every package)


def format_table(results: Mapping[str, Mapping[str, float]], paper: Mapping[str, float] | None = None) -> str:
    """Metrics side by side: one column per entry of ``results`` (e.g. ours, classical), then ``paper``."""
    cols = list(results)
    table = {name: dict(vals) for name, vals in results.items()}
    if paper is not None:
        cols.append("paper")
        table["paper"] = dict(paper)
    keys = [k for k in METRIC_KEYS if any(k in table[c] for c in cols)]
    label_w = max(len(_LABELS.get(k, k)) for k in keys)
    col_w = max(10, *(len(c) for c in cols))

    def cell(v: Any) -> str:
        if v is None:
            return "-".rjust(col_w)
        if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
            return str(int(v)).rjust(col_w)
        return f"{float(v):.4f}".rjust(col_w)

    lines = [" " * label_w + "  " + "  ".join(c.rjust(col_w) for c in cols)]
    for k in keys:
        lines.append(_LABELS.get(k, k).ljust(label_w) + "  " + "  ".join(cell(table[c].get(k)) for c in cols))
    return "\n".join(lines)
