"""Evaluation of trained actors (a run folder or an exported models folder) beside the classical baseline.

``evaluate_learned`` runs the learned pursuer team against learned evaders (the co-trained actors) or
scripted ones (``training.baselines.FleeingEvaders``), and the classical pursuer team against the same
evaders on the same evaluation seeds (``training.evaluate``: disjoint from every training seed), so that the
three columns of the printed table (ours, classical, paper) compare like with like.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from training.baselines import ClassicalPursuers, FleeingEvaders, Policy, TeamPolicy
from training.checkpoint import load_actors
from training.config import ExperimentConfig
from training.evaluate import EVAL_SEED_OFFSET, evaluate
from training.maddpg import ActorsPolicy, OnnxActorsPolicy

log = logging.getLogger(__name__)

EVADER_KINDS = ("learned", "scripted")


class LearnedModelError(ValueError):
    """A run or models folder cannot be evaluated; the message says why and what to do."""


def load_learned(run: str | Path | None = None, models: str | Path | None = None
                 ) -> tuple[ExperimentConfig, Policy, str]:
    """(experiment config, the learned policy for every agent, where it came from)."""
    if (run is None) == (models is None):
        raise LearnedModelError("give exactly one of --run RUN and --models DIR")
    if run is not None:
        run = Path(run)
        cfg_path = run / "config.toml"
        if not cfg_path.is_file():
            raise LearnedModelError(f"{run} is not a training run (no config.toml): train with "
                                    f"`swarm-train train --config CONFIG --out {run}`")
        cfg = ExperimentConfig.from_toml(cfg_path)
        spec, agents, _ = load_actors(run)
        if spec.hash != cfg.spec.hash:
            raise LearnedModelError(f"{run}/actors.pt has spec {spec.hash}, its config.toml {cfg.spec.hash}")
        return cfg, ActorsPolicy([a for _, _, a in agents], spec.max_obs_dim), str(run / "actors.pt")
    pol = OnnxActorsPolicy(str(models))
    conf = pol.manifest.config
    if not conf:
        raise LearnedModelError(f"{models}/manifest.json has no training config: re-export the run")
    cfg = ExperimentConfig.from_dict(conf)
    if cfg.spec.hash != pol.spec.hash:
        raise LearnedModelError(f"{models}: the manifest's config and spec disagree ({cfg.spec.hash} vs "
                                f"{pol.spec.hash}): re-export the run")
    return cfg, pol, str(Path(models) / "manifest.json")


def team(learned: Policy, evader: str) -> Policy:
    if evader == "learned":
        return learned
    if evader == "scripted":
        return TeamPolicy(learned, FleeingEvaders())
    raise LearnedModelError(f"--evader {evader!r}: use one of {list(EVADER_KINDS)}")


def evaluate_learned(run: str | Path | None = None, models: str | Path | None = None, evader: str = "learned",
                     episodes: int = 200, seed: int = 0, n_envs: int = 50, classical: bool = True,
                     progress: bool = True) -> dict[str, Any]:
    """The learned team's metrics under the evaluator's keys (``mean_min_dist`` ...), the same flat layout as
    the baselines' JSON, plus ``config``, ``source``, ``evader``, ``seed`` and ``classical``: the classical
    pursuer team's metrics against the same evaders on the same seeds."""
    cfg, learned, source = load_learned(run, models)
    ours = evaluate(cfg, team(learned, evader), episodes, seed=seed, n_envs=n_envs, progress=progress)
    out: dict[str, Any] = {**ours, "config": cfg.name, "spec_hash": cfg.spec.hash, "source": source,
                           "policy": "maddpg", "evader": evader, "seed": seed, "n_envs": n_envs,
                           "eval_seed_offset": EVAL_SEED_OFFSET}
    if classical:
        evaders = learned if evader == "learned" else FleeingEvaders()
        out["classical"] = evaluate(cfg, TeamPolicy(ClassicalPursuers(), evaders), episodes, seed=seed,
                                    n_envs=n_envs, progress=progress)
    return out


# ------------------------------------------------------------------------------------------------ CLI
# `swarm-train evaluate --run RUN | --models DIR` (training.cli routes here)


def add_learned_arguments(p: Any) -> None:
    p.add_argument("--run", metavar="RUN", help="evaluate the trained actors of a run folder (runs/NAME)")
    p.add_argument("--models", metavar="DIR", help="evaluate an exported ONNX models folder (models/NAME)")
    p.add_argument("--evader", choices=(*EVADER_KINDS, "both"), default="learned",
                   help="with --run/--models: the co-trained evader actors ('learned', default), the scripted "
                        "fleeing evaders ('scripted') or both (the JSON then holds one object per kind)")
    p.add_argument("--md", metavar="PATH", help="with --run/--models: also write the table as Markdown")
    p.add_argument("--no-classical", action="store_true",
                   help="with --run/--models: skip the classical pursuer team's column")


def markdown_table(results: dict[str, dict[str, Any]], paper: dict[str, float] | None) -> str:
    """One Markdown table: a column per result (``ours vs learned`` ...) and the paper's figures."""
    keys = ["mean_min_dist", "mean_avg_dist", "mean_max_dist", "tracking_rate", "coverage",
            "collisions_per_episode", "episodes"]
    cols = list(results)
    lines = ["| metric | " + " | ".join(cols) + (" | paper |" if paper else " |"),
             "|---" * (len(cols) + 1 + bool(paper)) + "|"]
    for k in keys:
        cells = [_cell(results[c].get(k)) for c in cols]
        if paper:
            cells.append(_cell(paper.get(k)))
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, int):
        return str(v)
    return f"{v:.4f}"


def cmd_evaluate_learned(args: Any) -> int:
    import json

    from training.cli import UsageError
    from training.evaluate import PAPER, format_table
    from training.checkpoint import CheckpointError
    kinds = list(EVADER_KINDS) if args.evader == "both" else [args.evader]
    results: dict[str, dict[str, Any]] = {}
    for kind in kinds:
        try:
            results[kind] = evaluate_learned(args.run, args.models, kind, args.episodes, args.seed, args.n_envs,
                                             classical=not args.no_classical, progress=not args.no_progress)
        except (LearnedModelError, CheckpointError, OSError) as exc:
            raise UsageError(str(exc)) from None
        except ValueError as exc:  # runtime.policy.PolicyError and spec errors
            raise UsageError(str(exc)) from None
    cols = {}
    for kind, res in results.items():
        cols[f"ours vs {kind}"] = res
        if "classical" in res:
            cols[f"classical vs {kind}"] = res["classical"]
    first = next(iter(results.values()))
    paper = PAPER.get(first["config"])
    print(f"{first['config']}: {first['source']} vs {' and '.join(kinds)} evaders, {first['episodes']} episodes "
          f"each, held-out seed {args.seed}, {sum(r['wall_s'] for r in results.values()):.1f} s")
    print(format_table(cols, paper))
    if args.json:
        p = Path(args.json)
        p.parent.mkdir(parents=True, exist_ok=True)
        doc = results[kinds[0]] if len(kinds) == 1 else results
        p.write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
        print(f"wrote {args.json}")
    if getattr(args, "md", None):
        p = Path(args.md)
        p.parent.mkdir(parents=True, exist_ok=True)
        head = (f"{first['config']}: `{first['source']}`, {first['episodes']} held-out episodes per column "
                f"(evaluation seed {args.seed}, seed offset {first['eval_seed_offset']})\n\n")
        p.write_text(head + markdown_table(cols, paper))
        print(f"wrote {args.md}")
    return 0


# ------------------------------------------------------------------------------------------------ plots
# `swarm-train plot --run RUN` (training.cli routes here)

_ROLE_COLORS = {"pursuer": "tab:red", "scout": "tab:blue", "evader": "tab:green"}


def _read_metrics(run: Path) -> dict[str, list[float]]:
    import csv
    path = run / "metrics.csv"
    if not path.is_file():
        raise LearnedModelError(f"{run} has no metrics.csv: is it a training run folder?")
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise LearnedModelError(f"{path} has no rows yet: train longer than train.log_every steps")
    cols: dict[str, list[float]] = {}
    for k in rows[0]:
        vals = [r.get(k) for r in rows]
        if all(v not in ("", None) for v in vals):  # None: a row written before the column existed
            cols[k] = [float(v) for v in vals]
    return cols


def plot_training_curves(run: str | Path, out_dir: str | Path) -> list[Path]:
    """``rewards.png`` (mean reward per step of each role vs frames: the paper's Fig. 3a/4a) and
    ``distances.png`` (min/mean/max pursuer-target distance vs frames: Fig. 3b/4b) from ``metrics.csv``."""
    from training.plots import plt  # Agg backend
    run, out_dir = Path(run), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    m = _read_metrics(run)
    x = np.asarray(m["frames"]) / 1e6

    def figure(name: str, ylabel: str, title: str, draw) -> Path:
        fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=120)
        draw(ax)
        ax.set_xlabel("frames [millions]")
        ax.set_ylabel(ylabel)
        ax.set_title(f"{run.name}: {title}")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out_dir / name)
        plt.close(fig)
        return out_dir / name

    def rewards(ax) -> None:
        for role, color in _ROLE_COLORS.items():
            if f"reward_{role}" in m:
                ax.plot(x, m[f"reward_{role}"], color=color, label=role)

    def distances(ax) -> None:
        for key, label, style in (("max_dist", "max", ":"), ("avg_dist", "mean", "-"), ("min_dist", "min", "--")):
            ax.plot(x, m[key], "k" + style, label=label)

    return [figure("rewards.png", "mean reward per agent and step", "rewards per role", rewards),
            figure("distances.png", "pursuer-target distance [m]",
                   "pursuer-target distances (training episodes)", distances)]


def cmd_plot_run(args: Any) -> int:
    from training.cli import UsageError
    from training.checkpoint import CheckpointError
    from training.plots import plot_episode, record_episode
    run = Path(args.run)
    out = Path(args.out) if args.out else run / "plots"
    try:
        paths = plot_training_curves(run, out)
        cfg, learned, _ = load_learned(run=run)
        evader = getattr(args, "evader", "learned")
        trace = record_episode(cfg, team(learned, evader), args.seed)
        paths.append(plot_episode(trace, out / "episode.png",
                                  f"{cfg.name}: learned team vs {evader} evaders, held-out seed {args.seed}"))
    except (LearnedModelError, CheckpointError) as exc:
        raise UsageError(str(exc)) from None
    for p in paths:
        print(f"wrote {p}")
    return 0
