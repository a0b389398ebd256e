"""Cross-play: the pursuer team of each run against the evaders of every run.

``swarm-train crossplay A B C`` evaluates, for every ordered pair (i, j), the pursuers and scouts of source i
(a training run or an exported models folder) against the evader actors of source j, on the same held-out
evaluation seeds, and the classical pursuer team against each source's evaders as an extra row. The diagonal
is self-play (what ``evaluate --evader learned`` reports); a row's mean over the columns says how good the
pursuers are, a column's how hard the evaders are, so that "vs learned" stops mixing pursuer quality with how
weak one run's evaders happen to be.
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from training.baselines import ClassicalPursuers, TeamPolicy
from training.evaluate import EVAL_SEED_OFFSET, evaluate, write_text_atomic
from training.learned_eval import LearnedModelError, load_sources

log = logging.getLogger(__name__)

CLASSICAL = "classical"
MATRIX_KEYS = ("mean_min_dist", "tracking_rate", "team_contacts_per_episode", "captures_per_episode")
"""The metrics kept for every cell."""


def source_names(sources: Sequence[str]) -> list[str]:
    """Short, distinct names: the folder's name, with its parent's where two folders share a name."""
    names = [Path(s).name or str(s) for s in sources]
    for i, n in enumerate(names):
        if names.count(n) > 1:
            names[i] = f"{Path(sources[i]).parent.name}/{n}"
    return [n if names.count(n) == 1 else f"{n}#{i}" for i, n in enumerate(names)]


def crossplay(sources: Sequence[str], episodes: int = 200, seed: int = 0, n_envs: int = 50,
              classical: bool = True, progress: bool = True) -> dict[str, Any]:
    """The cross-play matrices: ``matrix[key][i][j]`` = source i's pursuers vs source j's evaders, plus
    ``classical[key][j]`` (the classical team vs source j's evaders) and each row's and column's mean."""
    if len(sources) < 1:
        raise LearnedModelError("crossplay needs at least one run or models folder")
    loaded = load_sources(sources, "cross-play needs the same team and observation layout (runs of one "
                                   "configuration)")
    cfg = loaded[0][0]
    names = source_names(list(sources))
    n = len(loaded)
    cells: list[list[dict[str, float]]] = [[{} for _ in range(n)] for _ in range(n)]
    for i, (_, pursuers, _) in enumerate(loaded):
        for j, (_, evaders, _) in enumerate(loaded):
            m = evaluate(cfg, TeamPolicy(pursuers, evaders), episodes, seed=seed, n_envs=n_envs,
                         progress=progress, desc=f"{names[i]} vs {names[j]}")
            cells[i][j] = {k: m[k] for k in MATRIX_KEYS}
    doc: dict[str, Any] = {
        "config": cfg.name, "spec_hash": cfg.spec.hash, "names": names, "sources": [s for _, _, s in loaded],
        "episodes": episodes, "seed": seed, "n_envs": n_envs, "eval_seed_offset": EVAL_SEED_OFFSET,
        "matrix": {k: [[cells[i][j][k] for j in range(n)] for i in range(n)] for k in MATRIX_KEYS}}
    if classical:
        row = [evaluate(cfg, TeamPolicy(ClassicalPursuers(), ev), episodes, seed=seed, n_envs=n_envs,
                        progress=progress, desc=f"classical vs {names[j]}") for j, (_, ev, _) in enumerate(loaded)]
        doc["classical"] = {k: [r[k] for r in row] for k in MATRIX_KEYS}
    doc["pursuer_mean"] = {k: np.mean(doc["matrix"][k], axis=1).tolist() for k in MATRIX_KEYS}
    doc["evader_mean"] = {k: np.mean(doc["matrix"][k], axis=0).tolist() for k in MATRIX_KEYS}
    return doc


def format_matrix(doc: dict[str, Any], key: str, fmt: str = "{:.3f}", markdown: bool = False) -> str:
    """One metric's matrix: rows = pursuers of each source (then the classical team), columns = evaders."""
    names = doc["names"]
    head = ["pursuers \\ evaders", *names, "row mean"]
    rows = [[names[i], *(fmt.format(v) for v in doc["matrix"][key][i]), fmt.format(doc["pursuer_mean"][key][i])]
            for i in range(len(names))]
    if "classical" in doc:
        cl = doc["classical"][key]
        rows.append([CLASSICAL, *(fmt.format(v) for v in cl), fmt.format(float(np.mean(cl)))])
    rows.append(["column mean", *(fmt.format(v) for v in doc["evader_mean"][key]), ""])
    if markdown:
        return "\n".join(["| " + " | ".join(head) + " |", "|---" * len(head) + "|",
                          *("| " + " | ".join(r) + " |" for r in rows)]) + "\n"
    w = [max(len(r[c]) for r in [head, *rows]) for c in range(len(head))]
    return "\n".join("  ".join(cell.rjust(w[c]) if c else cell.ljust(w[c]) for c, cell in enumerate(r))
                     for r in [head, *rows]) + "\n"


_TITLES = {"mean_min_dist": "mean min pursuer-target distance [m] (lower: better pursuers / weaker evaders)",
           "tracking_rate": "tracking rate (higher: better pursuers)",
           "team_contacts_per_episode": "team contacts / episode (teammate + team-obstacle)",
           "captures_per_episode": "captures / episode"}


def report(doc: dict[str, Any], markdown: bool = False) -> str:
    head = (f"{doc['config']}: cross-play of {len(doc['names'])} sources, {doc['episodes']} held-out episodes "
            f"per cell (evaluation seed {doc['seed']}, seed offset {doc['eval_seed_offset']})\n")
    parts = [head]
    for k in ("mean_min_dist", "tracking_rate", "team_contacts_per_episode"):
        parts.append(("\n" if markdown else "") + _TITLES[k] + ("\n\n" if markdown else "\n"))
        parts.append(format_matrix(doc, k, "{:.2f}" if k.endswith("per_episode") else "{:.3f}", markdown))
    return "".join(parts)


# ------------------------------------------------------------------------------------------------ CLI


def add_crossplay(sub: Any) -> None:
    from training.cli import _positive_int
    p = sub.add_parser(
        "crossplay", help="pursuers of each run against the evaders of every run (a matrix)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="For every ordered pair of sources (training runs or models folders of one configuration), "
                    "the pursuer team (pursuers and scouts)\nof the row's source against the evaders of the "
                    "column's source, on the same held-out evaluation seeds; the classical team\nagainst each "
                    "source's evaders as an extra row. Prints the matrices of mean min distance, tracking rate "
                    "and\nteam contacts, with row means (pursuer quality) and column means (evader strength).",
        epilog="example:\n  swarm-train crossplay runs/rb_s0 runs/rb_s1 runs/rb_s2 --episodes 200 --seed 1000 "
               "--json results/crossplay_rb.json --md results/crossplay_rb.md")
    p.add_argument("sources", nargs="+", metavar="RUN_OR_MODELS",
                   help="training run folders (runs/NAME) or exported models folders (models/NAME); quoted globs "
                        "expand")
    p.add_argument("--episodes", type=_positive_int, default=200, metavar="N", help="episodes per cell (default 200)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="evaluation seed (default 0)")
    p.add_argument("--n-envs", type=_positive_int, default=50, metavar="K",
                   help="episodes stepped together (default 50)")
    p.add_argument("--json", metavar="PATH", help="write the matrices to this JSON file")
    p.add_argument("--md", metavar="PATH", help="write the matrices as Markdown tables")
    p.add_argument("--no-classical", action="store_true", help="skip the classical team's row")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_crossplay)


def cmd_crossplay(args: Any) -> int:
    from training.aggregate import expand_sources
    from training.checkpoint import CheckpointError
    from training.cli import UsageError
    try:
        doc = crossplay(expand_sources(args.sources), args.episodes, args.seed, args.n_envs,
                        classical=not args.no_classical, progress=not args.no_progress)
    except (CheckpointError, ValueError) as exc:  # LearnedModelError, runtime.policy.PolicyError
        raise UsageError(str(exc)) from None
    print(report(doc), end="")
    try:
        if args.json:
            write_text_atomic(args.json, json.dumps(doc, indent=2, sort_keys=True) + "\n")
            print(f"wrote {args.json}")
        if args.md:
            write_text_atomic(args.md, report(doc, markdown=True))
            print(f"wrote {args.md}")
    except OSError as exc:
        raise UsageError(f"cannot write the output: {exc}") from None
    return 0
