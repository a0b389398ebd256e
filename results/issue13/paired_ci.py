"""How sure is a "win"? Each run's team and the classical team meet the same episodes (same seeds, the same
scripted evaders with the same drawn parameters), so their difference can be taken episode by episode. For each run
and evader kind: the mean per-episode difference learned - classical in min distance [m] and in tracking rate, with
a paired bootstrap 95% interval over the episodes (10,000 resamples from one generator, seeded 0, drawn in the
order printed: another selection of runs or kinds moves an interval's ends by about 0.0001), and whether the interval
excludes 0. The same episodes as `swarm-train evaluate --episodes 200 --seed 0` (evaluation seed 0, 50 envs a round);
`--seed 0,1,2` pools the episodes of several evaluation seeds (each the episodes of `swarm-train evaluate --seed S`,
each scripted kind drawing its parameters from that seed) into one interval, and prints each seed's mean difference
beside it.

    .venv/bin/python results/issue13/paired_ci.py RUN [RUN ...] [--evader suite:perimeter,hider,juker] [--episodes 200]
        [--seed 0 | --seed 0,1,2] [--json PATH]

``--json``: also write, per run, kind and evaluation seed, both teams' means (min distance, tracking, coverage,
teammate and team-obstacle contacts per episode) and each pooled interval, so that the wins, the contacts and the
coverage of every seed are read off the same episodes as the intervals.
"""
import argparse
import json
import os

import numpy as np

from runtime.metrics import summarize
from training.evader_spec import expand, label
from training.learned_eval import evaluate_kind, load_source

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("runs", nargs="+", help="run folders (runs/NAME_sS) or models folders")
p.add_argument("--evader", default="suite:perimeter,hider,juker", help="as swarm-train evaluate's --evader")
p.add_argument("--episodes", type=int, default=200)
p.add_argument("--seed", default="0", help="evaluation seed, or several comma-separated to pool (default 0)")
p.add_argument("--json", help="also write every seed's means of both teams and the pooled intervals here")
args = p.parse_args()
try:
    seeds = [int(x) for x in args.seed.split(",")]
except ValueError:
    p.error(f"--seed: {args.seed!r} is not an integer or a comma-separated list of integers (e.g. 0 or 0,1,2)")
if len(set(seeds)) != len(seeds):
    p.error(f"--seed: {args.seed!r} names a seed twice, which would count its episodes twice: give each seed once")
rng = np.random.default_rng(0)


def ci(d: np.ndarray) -> tuple[float, float, float]:
    boot = d[rng.integers(0, d.size, (10_000, d.size))].mean(1)
    return float(d.mean()), float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))


def cell(m: float, lo: float, hi: float, lower_is_better: bool) -> str:
    """The mean difference, its interval, and "better" or "worse" when the interval excludes 0."""
    below, above = hi < 0, lo > 0
    verdict = ("better" if below else "worse" if above else "") if lower_is_better else \
        ("better" if above else "worse" if below else "")
    return f"{m:+.4f} [{lo:+.4f}, {hi:+.4f}]" + (f" {verdict}" if verdict else "")


if len(seeds) == 1:
    print(f"{args.episodes} episodes per kind, evaluation seed {seeds[0]}; learned - classical, paired bootstrap 95%")
else:
    print(f"{args.episodes} episodes per kind and evaluation seed, seeds {args.seed} pooled "
          f"({args.episodes * len(seeds)} episodes); learned - classical, paired bootstrap 95%, then each seed's mean")


JSON_KEYS = {"min_dist": "mean_min_dist", "tracking_rate": "tracking_rate", "coverage": "coverage",
             "teammate_per_episode": "teammate_contacts_per_episode",
             "team_obstacle_per_episode": "team_obstacle_contacts_per_episode",
             "team_contacts_per_episode": "team_contacts_per_episode"}
"""This file's JSON keys and the ``runtime.metrics.summarize`` keys they hold."""


def means(records: list) -> dict[str, float]:
    """One team's per-episode means over ``records`` (``summarize``), under this file's JSON keys."""
    s = summarize(records)
    return {ours: s[theirs] for ours, theirs in JSON_KEYS.items()}


doc: dict = {"episodes": args.episodes, "seeds": seeds, "evader": args.evader, "runs": {}}
for run in args.runs:
    cfg, learned, name = load_source(run)
    for kind in expand(args.evader):
        dd, dt = [], []
        entry = doc["runs"].setdefault(run, {})[label(kind)] = {"per_seed": {}}
        for seed in seeds:
            ours: list = []
            theirs: list = []
            evaluate_kind(cfg, learned, kind, args.episodes, seed, n_envs=50, classical=True, progress=False,
                          records=(ours, theirs))
            dd.append(np.array([a.min_dist - b.min_dist for a, b in zip(ours, theirs)]))
            dt.append(np.array([a.tracking_rate - b.tracking_rate for a, b in zip(ours, theirs)]))
            entry["per_seed"][str(seed)] = {"learned": means(ours), "classical": means(theirs)}
        entry["min_dist_diff"] = dict(zip(("mean", "lo", "hi"), ci(np.concatenate(dd))))
        entry["tracking_diff"] = dict(zip(("mean", "lo", "hi"), ci(np.concatenate(dt))))
        md, td = entry["min_dist_diff"], entry["tracking_diff"]
        line = (f"{run:28s} {label(kind):10s} min dist {cell(md['mean'], md['lo'], md['hi'], True):44s} "
                f"tracking {cell(td['mean'], td['lo'], td['hi'], False)}")
        if len(seeds) > 1:
            line += ("  per seed: " + ", ".join(f"{x.mean():+.4f} / {y.mean():+.4f}" for x, y in zip(dd, dt)))
        print(line, flush=True)
if args.json:
    tmp = args.json + ".tmp"
    with open(tmp, "w") as f:
        json.dump(doc, f, indent=1)
    os.replace(tmp, args.json)
    print(f"wrote {args.json}")
