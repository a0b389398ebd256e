"""Evaluation of trained actors (a run folder or an exported models folder) beside the classical baseline.

``evaluate_learned`` runs the learned pursuer team against one kind of evaders (``training.evader_spec``: the
co-trained actors, the scripted fleeing evaders, a kind of the held-out suite or a user's class), and the
classical pursuer team against the same evaders on the same evaluation seeds (``training.evaluate``: disjoint
from every training seed), so that the columns of the printed table (ours, classical, paper) compare like with
like. Several runs at once: ``training.aggregate``.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from training.baselines import ClassicalPursuers, Policy, TeamPolicy
from training.checkpoint import load_actors
from training.config import ExperimentConfig
from training.evader_spec import SUITE_MEAN, expand, label, make_evaders
from training.evaluate import EVAL_SEED_OFFSET, evaluate, mean_of
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
        run, actors = _run_and_actors(Path(run))
        cfg_path = run / "config.toml"
        if not cfg_path.is_file():
            raise LearnedModelError(f"{run} is not a training run (no config.toml): train with "
                                    f"`swarm-train train --config CONFIG --out {run}`")
        cfg = ExperimentConfig.from_toml(cfg_path)
        spec, agents, _ = load_actors(actors)
        if spec.hash != cfg.spec.hash:
            raise LearnedModelError(f"{actors} has spec {spec.hash}, its run's config.toml {cfg.spec.hash}")
        return cfg, ActorsPolicy([a for _, _, a in agents], spec.max_obs_dim, spec), str(actors)
    if not (Path(models) / "manifest.json").is_file():
        raise LearnedModelError(f"{models} is not a models folder (no manifest.json): export a run with "
                                f"`swarm-export onnx --run RUN --out {models}`")
    pol = OnnxActorsPolicy(str(models))
    conf = pol.manifest.config
    if not conf:
        raise LearnedModelError(f"{models}/manifest.json has no training config: re-export the run")
    cfg = ExperimentConfig.from_dict(conf)
    if cfg.spec.hash != pol.spec.hash:
        raise LearnedModelError(f"{models}: the manifest's config and spec disagree ({cfg.spec.hash} vs "
                                f"{pol.spec.hash}): re-export the run")
    return cfg, pol, str(Path(models) / "manifest.json")


def _run_and_actors(path: Path) -> tuple[Path, Path]:
    """(run folder, actors file) of ``--run PATH``: a run folder (its ``actors.pt``) or one of its actor files
    (``runs/NAME/snapshots/actors_006000.pt``, ``runs/NAME/actors_imitation.pt``: the run is the nearest folder
    above it with a ``config.toml``)."""
    if not path.is_file():
        return path, path / "actors.pt"
    for parent in path.parents:
        if (parent / "config.toml").is_file():
            return parent, path
    raise LearnedModelError(f"{path}: no folder above it holds a config.toml; give a run folder or an actors file "
                            f"inside one")


def load_source(path: str | Path) -> tuple[ExperimentConfig, Policy, str]:
    """``load_learned`` of a run folder (has ``config.toml``) or one of its actor files, or of a models folder
    (has ``manifest.json``)."""
    p = Path(path)
    if (p / "config.toml").is_file() or p.is_file():
        return load_learned(run=p)
    if (p / "manifest.json").is_file():
        return load_learned(models=p)
    raise LearnedModelError(f"{str(path)!r} is neither a training run (config.toml) nor a models folder "
                            f"(manifest.json): give runs/NAME or models/NAME")


def load_sources(paths: Sequence[str | Path], why: str) -> list[tuple[ExperimentConfig, Policy, str]]:
    """``load_source`` of each path, all of one spec (``why``: what needs that, for the error)."""
    loaded = [load_source(s) for s in paths]
    first = loaded[0]
    for c, _, src in loaded[1:]:
        if c.spec.hash != first[0].spec.hash:
            raise LearnedModelError(f"{src} has spec {c.spec.hash}, {first[2]} has {first[0].spec.hash}: {why}")
    return loaded


def team(learned: Policy, evader: str, seed: int = 0) -> Policy:
    """The learned pursuer team against one expanded evader kind (``training.evader_spec.expand``)."""
    if evader == "learned":
        return learned
    return TeamPolicy(learned, make_evaders(evader, seed, learned))


def evaluate_kind(cfg: ExperimentConfig, learned: Policy, kind: str, episodes: int, seed: int, n_envs: int,
                  classical: bool, progress: bool, records: tuple[list, list] | None = None) -> dict[str, Any]:
    """The learned team's metrics against one evader kind, and the classical team's (key ``classical``)
    against a fresh copy of the same evaders (scripted evaders draw the same parameters from the same seed).
    ``records``: two lists that receive the learned and the classical team's episodes, paired episode for episode
    (``evaluate``'s ``records_out``)."""
    name = label(kind)
    ours, theirs = records or (None, None)
    out: dict[str, Any] = evaluate(cfg, team(learned, kind, seed), episodes, seed=seed, n_envs=n_envs,
                                   progress=progress, desc=f"ours vs {name}", records_out=ours)
    if classical:
        out["classical"] = evaluate(cfg, TeamPolicy(ClassicalPursuers(), make_evaders(kind, seed, learned)),
                                    episodes, seed=seed, n_envs=n_envs, progress=progress,
                                    desc=f"classical vs {name}", records_out=theirs)
    return out


def with_suite_mean(results: dict[str, dict[str, Any]], kinds: list[str]) -> dict[str, dict[str, Any]]:
    """Adds ``SUITE_MEAN`` (the mean over the suite's kinds, ``classical`` too) when more than one ran."""
    suite = [label(k) for k in kinds if k.startswith("suite:")]
    if len(suite) > 1:
        mean: dict[str, Any] = mean_of([results[k] for k in suite])
        if all("classical" in results[k] for k in suite):
            mean["classical"] = mean_of([results[k]["classical"] for k in suite])
        mean["kinds"] = suite
        results[SUITE_MEAN] = mean
    return results


def evaluate_learned(run: str | Path | None = None, models: str | Path | None = None, evader: str = "learned",
                     episodes: int = 200, seed: int = 0, n_envs: int = 50, classical: bool = True,
                     progress: bool = True) -> dict[str, Any]:
    """The learned team's metrics under the evaluator's keys (``mean_min_dist`` ...), the same flat layout as
    the baselines' JSON, plus ``config``, ``source``, ``evader``, ``seed`` and ``classical``: the classical
    pursuer team's metrics against the same evaders on the same seeds. ``evader`` is one kind (``learned``,
    ``scripted``, ``suite:KIND``, ``module:Class``); for several see ``evaluate_learned_kinds``."""
    kinds = expand(evader)
    if len(kinds) != 1:
        raise LearnedModelError(f"--evader {evader!r} stands for {len(kinds)} kinds: evaluate them with "
                                f"evaluate_learned_kinds")
    return evaluate_learned_kinds(run, models, kinds, episodes, seed, n_envs, classical, progress)[label(kinds[0])]


def evaluate_learned_kinds(run: str | Path | None, models: str | Path | None, kinds: list[str], episodes: int,
                           seed: int, n_envs: int, classical: bool = True, progress: bool = True
                           ) -> dict[str, dict[str, Any]]:
    """``evaluate_learned``'s document for each expanded kind, by ``label(kind)``, plus ``SUITE_MEAN``."""
    cfg, learned, source = load_learned(run, models)
    results: dict[str, dict[str, Any]] = {}
    for kind in kinds:
        res = evaluate_kind(cfg, learned, kind, episodes, seed, n_envs, classical, progress)
        results[label(kind)] = {**res, "config": cfg.name, "spec_hash": cfg.spec.hash, "source": source,
                                "policy": "maddpg", "evader": kind, "seed": seed, "n_envs": n_envs,
                                "eval_seed_offset": EVAL_SEED_OFFSET}
    return with_suite_mean(results, kinds)


# ------------------------------------------------------------------------------------------------ CLI
# `swarm-train evaluate --run RUN | --models DIR` (training.cli routes here)

EVADER_HELP = (
    "evaders to meet: 'learned' (the co-trained evader actors; needs --run/--models; default there), "
    "'scripted' (training.baselines.FleeingEvaders), 'both' (learned and scripted), 'suite' (every kind of the "
    "held-out suite, each reported alone, and their mean), 'all' (learned, scripted and the suite), 'A+B' (both "
    "lists), 'suite:KIND[,KIND]' (KIND: wanderer, perimeter, "
    "hider, juker, predictive), 'module:Class' or 'path/to/file.py:Class' (your own evaders: act(obs, env) "
    "-> [B, N, 2], built with Class(seed=S) or Class()). Without --run/--models it replaces --evaders.")


def add_learned_arguments(p: Any) -> None:
    p.add_argument("--run", metavar="RUN", action="append",
                   help="evaluate the trained actors of a run folder (runs/NAME), or one of its actor files "
                        "(runs/NAME/actors_imitation.pt, runs/NAME/snapshots/actors_006000.pt); give it several "
                        "times or as a quoted glob ('runs/role_based_s*') to report the mean and min-max over runs")
    p.add_argument("--models", metavar="DIR", action="append",
                   help="evaluate an exported ONNX models folder (models/NAME); several as with --run")
    p.add_argument("--evader", metavar="SPEC", default=None, help=EVADER_HELP)
    p.add_argument("--md", metavar="PATH", help="also write the table as Markdown (ready to paste)")
    p.add_argument("--no-classical", action="store_true",
                   help="with --run/--models: skip the classical pursuer team's column")


def markdown_table(results: dict[str, dict[str, Any]], paper: dict[str, float] | None) -> str:
    """One Markdown table: a column per result (``ours vs learned`` ...) and the paper's figures."""
    keys = ["mean_min_dist", "mean_avg_dist", "mean_max_dist", "tracking_rate", "coverage",
            "teammate_contacts_per_episode", "team_obstacle_contacts_per_episode", "evader_contacts_per_episode",
            "collisions_per_episode", "captures_per_episode", "episodes"]
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


def columns(results: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """``ours vs K`` and ``classical vs K`` columns of every kind's result."""
    cols = {}
    for kind, res in results.items():
        name = "suite mean" if kind == SUITE_MEAN else kind
        cols[f"ours vs {name}"] = res
        if "classical" in res:
            cols[f"classical vs {name}"] = res["classical"]
    return cols


def cmd_evaluate_learned(args: Any) -> int:
    import json

    from training.cli import UsageError
    from training.aggregate import cmd_evaluate_runs, expand_sources
    from training.evaluate import PAPER, format_table, write_text_atomic
    runs, models = expand_sources(args.run or []), expand_sources(args.models or [])
    if len(runs) + len(models) > 1:
        if getattr(args, "plot", None):
            raise UsageError(f"--plot {args.plot}: draws one team's episode, and {len(runs) + len(models)} teams "
                             f"are given: give one --run or --models with --plot (or leave --plot out)")
        return cmd_evaluate_runs(args)
    kinds = expand(args.evader or "learned")
    results = evaluate_learned_kinds(runs[0] if runs else None, models[0] if models else None, kinds,
                                     args.episodes, args.seed, args.n_envs, classical=not args.no_classical,
                                     progress=not args.no_progress)
    cols = columns(results)
    first = next(iter(results.values()))
    paper = PAPER.get(first["config"])
    names = [label(k) for k in kinds]
    wall = sum(r["wall_s"] + r.get("classical", {}).get("wall_s", 0.0) for k, r in results.items() if k != SUITE_MEAN)
    print(f"{first['config']}: {first['source']} vs {', '.join(names)} evaders, {first['episodes']} episodes "
          f"each, held-out seed {args.seed}, {wall:.1f} s")
    print(format_table(cols, paper))
    try:
        if args.json:
            doc = results[names[0]] if len(kinds) == 1 else results
            write_text_atomic(args.json, json.dumps(doc, indent=2, sort_keys=True) + "\n")
            print(f"wrote {args.json}")
        if getattr(args, "md", None):
            head = (f"{first['config']}: `{first['source']}`, {first['episodes']} held-out episodes per column "
                    f"(evaluation seed {args.seed}, seed offset {first['eval_seed_offset']})\n\n")
            write_text_atomic(args.md, head + markdown_table(cols, paper))
            print(f"wrote {args.md}")
    except OSError as exc:
        raise UsageError(f"cannot write the output: {exc}") from None
    if getattr(args, "plot", None):  # one episode of this team against the first kind of evaders
        from training.cli import _plot
        cfg, learned, _ = load_learned(run=runs[0] if runs else None, models=models[0] if models else None)
        _plot(cfg, team(learned, kinds[0], args.seed), args.seed, args.plot,
              f"{first['source']} vs {names[0]} evaders, {cfg.name}, held-out seed {args.seed}")
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
        from runtime.cliutil import atomic_path
        with atomic_path(out_dir / name) as tmp:  # a picture is whole or absent, never half-written
            fig.savefig(tmp)
        plt.close(fig)
        return out_dir / name

    def rewards(ax) -> None:
        for role, color in _ROLE_COLORS.items():
            if f"reward_{role}" in m:
                ax.plot(x, m[f"reward_{role}"], color=color, label=role)

    def distances(ax) -> None:
        for key, name, style in (("max_dist", "max", ":"), ("avg_dist", "mean", "-"), ("min_dist", "min", "--")):
            ax.plot(x, m[key], "k" + style, label=name)

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
        kinds = expand(evader)
        if len(kinds) != 1:
            raise LearnedModelError(f"--evader {evader!r}: plot draws one episode against one kind of evaders: "
                                    f"give one of {kinds}")
        trace = record_episode(cfg, team(learned, kinds[0], args.seed), args.seed)
        paths.append(plot_episode(trace, out / "episode.png",
                                  f"{cfg.name}: learned team vs {evader} evaders, held-out seed {args.seed}"))
    except (LearnedModelError, CheckpointError, ValueError) as exc:  # EvaderSpecError too
        raise UsageError(str(exc)) from None
    for p in paths:
        print(f"wrote {p}")
    return 0
