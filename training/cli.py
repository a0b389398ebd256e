"""``swarm-train``: evaluate policies against the paper's tables and draw episodes.

One function per subcommand (``add_<name>`` builds its parser, ``cmd_<name>`` runs it); a new subcommand is
one more pair and one line in ``build_parser``. Wrong configs and arguments print one ``error:`` line and
exit with status 2, without a traceback.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any, Callable

from runtime.cliutil import (ArgumentParser, atomic_path, check_in_file, check_out_dir, check_out_file, int_in,
                             out_picture, port, positive_int, recheck, seed)
from runtime.spec import SpecError

DEFAULT_CONFIG = "configs/role_based.toml"
EXIT_USAGE = 2


class UsageError(Exception):
    """A user input is wrong; the message says which and how to fix it."""


def _load_config(path: str):
    from training.config import ExperimentConfig
    return ExperimentConfig.from_toml(path)


def _add_config(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=DEFAULT_CONFIG, metavar="PATH",
                   help=f"experiment TOML (training.config.ExperimentConfig; default {DEFAULT_CONFIG})")


def _add_policy(p: argparse.ArgumentParser) -> None:
    from training.baselines import EVADER_NAMES, POLICY_NAMES
    p.add_argument("--policy", choices=POLICY_NAMES, default="classical",
                   help="pursuer team (pursuers and scouts): 'classical' = Hungarian pursuit + Lloyd scouts "
                        "(centralized, full information), 'random' = uniform random actions (default classical)")
    p.add_argument("--evaders", choices=EVADER_NAMES, default="classical",
                   help="evader policy: 'classical' = flee the pursuer team, avoid walls and obstacles; "
                        "'random' = uniform random (default classical)")


_positive_int = positive_int  # crossplay imports it under this name

episodes = int_in(1, 1_000_000, "episodes")
"""Episodes an evaluation runs at most; more is a typo (the paper's tables use 200 to 1000)."""
n_envs = int_in(1, 65_536, "envs")
"""Environments stepped together at most: their state is allocated at once."""
threads = int_in(1, 256, "threads")
"""Torch CPU threads at most (each one a thread of its own; thousands fail to start)."""


# ------------------------------------------------------------------------------------------- evaluate


def add_evaluate(sub: Any) -> None:
    p = sub.add_parser(
        "evaluate", help="run a policy for N episodes and report the paper's metrics",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Runs exactly --episodes episodes on evaluation seeds (disjoint from training seeds, see "
                    "training.evaluate), prints the metrics beside the paper's figures and optionally writes "
                    "them as JSON (and Markdown) and draws one episode (run alone on seed S).\n\n"
                    "Collisions are split by whose fault they are: teammate contacts (pursuer/scout with "
                    "pursuer/scout),\nteam-obstacle contacts and evader-side contacts (evaders with each other "
                    "or obstacles); captures apart.",
        epilog="examples:\n"
               "  swarm-train evaluate --policy classical --evader suite --episodes 50 --seed 1000\n"
               "  swarm-train evaluate --models models/role_based --evader both --md results/rb.md\n"
               "  swarm-train evaluate --models models/role_based --evader suite:wanderer,hider\n"
               "  swarm-train evaluate --run runs/rb_s0 --evader my_evaders.py:Sneaky\n"
               "  swarm-train evaluate --run 'runs/rb_s*' --evader suite --md results/rb_seeds.md   "
               "(mean and min-max over runs)")
    _add_config(p)
    _add_policy(p)
    p.add_argument("--episodes", type=episodes, default=200, metavar="N",
                   help="episodes per evaluated column (default 200)")
    p.add_argument("--seed", type=seed, default=0, metavar="S", help="evaluation seed (default 0)")
    p.add_argument("--n-envs", type=n_envs, default=50, metavar="K",
                   help="episodes stepped together (default 50); the episodes drawn depend on it")
    p.add_argument("--json", metavar="PATH", help="write the metrics and the run's settings to this JSON file")
    p.add_argument("--plot", metavar="PNG", help="also draw one episode (seed S) to this PNG")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from training.learned_eval import add_learned_arguments
    add_learned_arguments(p)
    p.set_defaults(func=cmd_evaluate)


def cmd_evaluate(args: argparse.Namespace) -> int:
    from training.checkpoint import CheckpointError
    try:
        if args.run or args.models:
            from training.learned_eval import cmd_evaluate_learned
            return cmd_evaluate_learned(args)
        return _evaluate_baseline(args)
    except (CheckpointError, OSError, ValueError) as exc:  # LearnedModelError, EvaderSpecError, PolicyError
        raise UsageError(str(exc)) from None


def _evaluate_baseline(args: argparse.Namespace) -> int:
    from training.baselines import make_policy
    from training.evaluate import EVAL_SEED_OFFSET, PAPER, evaluate, format_table

    cfg = _load_config(args.config)
    if args.evader is not None:
        return _evaluate_baseline_vs(args, cfg)
    policy = make_policy(args.policy, seed=args.seed, evaders=args.evaders)
    metrics = evaluate(cfg, policy, args.episodes, seed=args.seed, n_envs=args.n_envs,
                       progress=not args.no_progress)
    label = args.policy if args.evaders == "classical" else f"{args.policy} vs {args.evaders}"
    print(f"{cfg.name}: {args.policy} pursuer team vs {args.evaders} evaders, {metrics['episodes']} episodes, "
          f"seed {args.seed}, {metrics['wall_s']:.1f} s")
    print(format_table({label: metrics}, PAPER.get(cfg.name)))
    if args.json:
        doc = {**metrics, "config": cfg.name, "config_path": str(args.config), "spec_hash": cfg.spec.hash,
               "policy": args.policy, "evaders": args.evaders, "seed": args.seed, "n_envs": args.n_envs,
               "eval_seed_offset": EVAL_SEED_OFFSET}
        _write_json(args.json, doc)
        print(f"wrote {args.json}")
    if args.md:
        _write_md(args.md, f"{cfg.name}: {label}, {metrics['episodes']} episodes (evaluation seed {args.seed}, seed "
                           f"offset {EVAL_SEED_OFFSET})", {label: metrics}, PAPER.get(cfg.name))
    if args.plot:
        _plot(cfg, make_policy(args.policy, seed=args.seed, evaders=args.evaders), args.seed, args.plot,
              f"{label}, {cfg.name}, seed {args.seed}")
    return 0


def _evaluate_baseline_vs(args: argparse.Namespace, cfg) -> int:
    """``--policy P --evader SPEC`` without a run: the baseline team against each kind SPEC stands for."""
    from training.baselines import TeamPolicy, make_policy
    from training.evader_spec import SUITE_MEAN, expand, label, make_evaders
    from training.evaluate import EVAL_SEED_OFFSET, PAPER, evaluate, format_table
    from training.learned_eval import with_suite_mean

    kinds = expand(args.evader)
    pursuers = make_policy(args.policy, seed=args.seed).pursuer_team
    results: dict[str, dict] = {}
    for kind in kinds:
        m = evaluate(cfg, TeamPolicy(pursuers, make_evaders(kind, args.seed)), args.episodes, seed=args.seed,
                     n_envs=args.n_envs, progress=not args.no_progress, desc=f"{args.policy} vs {label(kind)}")
        results[label(kind)] = {**m, "config": cfg.name, "config_path": str(args.config),
                                "spec_hash": cfg.spec.hash, "policy": args.policy, "evader": kind,
                                "seed": args.seed, "n_envs": args.n_envs, "eval_seed_offset": EVAL_SEED_OFFSET}
    results = with_suite_mean(results, kinds)
    cols = {f"{args.policy} vs {'suite mean' if k == SUITE_MEAN else k}": v for k, v in results.items()}
    wall = sum(r["wall_s"] for k, r in results.items() if k != SUITE_MEAN)
    print(f"{cfg.name}: {args.policy} pursuer team vs {', '.join(label(k) for k in kinds)} evaders, "
          f"{args.episodes} episodes each, seed {args.seed}, {wall:.1f} s")
    print(format_table(cols, PAPER.get(cfg.name)))
    if args.json:
        _write_json(args.json, results[label(kinds[0])] if len(kinds) == 1 else results)
        print(f"wrote {args.json}")
    if args.md:
        _write_md(args.md, f"{cfg.name}: {args.policy} pursuer team, {args.episodes} held-out episodes per column "
                           f"(evaluation seed {args.seed}, seed offset {EVAL_SEED_OFFSET})", cols, PAPER.get(cfg.name))
    if args.plot:
        _plot(cfg, TeamPolicy(pursuers, make_evaders(kinds[0], args.seed)), args.seed, args.plot,
              f"{args.policy} vs {label(kinds[0])}, {cfg.name}, seed {args.seed}")
    return 0


# ----------------------------------------------------------------------------------------------- plot


def add_plot(sub: Any) -> None:
    p = sub.add_parser(
        "plot", help="draw one episode of a policy, or a training run's curves and an episode",
        description="Runs one episode and draws it: arena, obstacles, pursuers red, scouts blue, targets "
                    "green, trails, sensing disks, the bounded Voronoi cells at the final step and the area "
                    "covered. With --run RUN: also the run's reward curves per role and min/mean/max distance "
                    "curves (rewards.png, distances.png, episode.png in --out, default RUN/plots/).")
    _add_config(p)
    _add_policy(p)
    p.add_argument("--seed", type=seed, default=0, metavar="S", help="episode seed (default 0)")
    p.add_argument("--out", metavar="PATH", help="PNG file to write (a folder with --run; default RUN/plots/)")
    p.add_argument("--run", metavar="RUN", help="a training run folder: plot its curves and its learned team")
    p.add_argument("--evader", metavar="SPEC", default="learned",
                   help="with --run: the evaders to draw against, as for `evaluate --evader` (one kind: 'learned', "
                        "default; 'scripted'; 'suite:KIND'; 'module:Class'; 'path/to/file.py:Class')")
    p.set_defaults(func=cmd_plot)


def cmd_plot(args: argparse.Namespace) -> int:
    if args.run:
        from training.learned_eval import cmd_plot_run
        return cmd_plot_run(args)
    if not args.out:
        raise UsageError("--out PNG is required (or give --run RUN to plot a training run)")
    from training.baselines import make_policy

    cfg = _load_config(args.config)
    policy = make_policy(args.policy, seed=args.seed, evaders=args.evaders)
    _plot(cfg, policy, args.seed, args.out, f"{args.policy} vs {args.evaders} evaders, {cfg.name}, seed {args.seed}")
    return 0


# ------------------------------------------------------------------------------------------- helpers


def _plot(cfg, policy, seed: int, out: str, title: str) -> None:
    from training.plots import plot_episode, record_episode
    trace = record_episode(cfg, policy, seed)
    try:
        with atomic_path(out) as tmp:  # never a half-drawn picture after an error or Ctrl-C
            plot_episode(trace, tmp, title)
    except OSError as exc:
        raise UsageError(f"cannot write {out!r}: {exc.strerror or exc}") from None
    print(f"wrote {out}")


def _write_json(path: str, doc: dict) -> None:
    from training.evaluate import write_text_atomic
    try:
        write_text_atomic(path, json.dumps(doc, indent=2, sort_keys=True) + "\n")
    except OSError as exc:
        raise UsageError(f"cannot write {path!r}: {exc.strerror or exc}") from None


def _write_md(path: str, head: str, cols: dict, paper) -> None:
    from training.evaluate import write_text_atomic
    from training.learned_eval import markdown_table
    try:
        write_text_atomic(path, head + "\n\n" + markdown_table(cols, paper))
    except OSError as exc:
        raise UsageError(f"cannot write {path!r}: {exc.strerror or exc}") from None
    print(f"wrote {path}")


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
        prog="swarm-train",
        description="Train, evaluate and draw the heterogeneous pursuit-evasion-exploration swarm.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    from training.sweep import add_sweep_parser
    from training.train import add_train_parser
    from training.crossplay import add_crossplay
    adders: list[Callable[[Any], None]] = [add_train_parser, add_evaluate, add_crossplay, add_plot,
                                           add_sweep_parser]
    for add in adders:
        add(sub)
    return parser


OUTPUT_FILES = ("json", "md", "plot")
"""Options of any subcommand that name a file to write: checked before the command starts work."""


def check_outputs(args: argparse.Namespace) -> None:
    """Every output path of ``args`` can be written (no file in the way, not a folder): else ``UsageError``
    naming the option, so that an evaluation or a training is not run for nothing."""
    for name in OUTPUT_FILES:
        path = getattr(args, name, None)
        if isinstance(path, str):
            try:
                (out_picture if name == "plot" else check_out_file)(path)
            except argparse.ArgumentTypeError as exc:
                raise UsageError(f"--{name}: {exc}") from None
    if args.command == "plot" and args.run and Path(args.run).exists() and not Path(args.run).is_dir():
        raise UsageError(f"--run: {args.run!r} is a file, not a training run folder; give the folder that "
                         f"`swarm-train train --out RUN` wrote")
    if args.command == "plot" and args.run is not None and not (Path(args.run) / "metrics.csv").is_file():
        raise UsageError(f"--run: {args.run!r} is not a training run folder (no metrics.csv in it); give the folder "
                         f"that `swarm-train train --out RUN` wrote")
    if args.command == "plot" and args.out is not None:  # a folder with --run, else the PNG
        try:
            (check_out_dir if args.run else out_picture)(args.out)
        except argparse.ArgumentTypeError as exc:
            raise UsageError(f"--out: {exc}") from None


RECHECKED = (("seed", seed), ("n_envs", n_envs), ("threads", threads), ("episodes", episodes))
"""Options that parsers outside this module (train, crossplay) register with a looser type, checked again here
with this module's types."""


def _check_ray(address: str) -> None:
    """``--ray``: 'local', 'auto', ray://HOST[:PORT] or HOST:PORT (Ray fails on anything else only after the
    sweep's configs were read, with a traceback)."""
    rest = address[len("ray://"):] if address.startswith("ray://") else address
    host, colon, port_text = rest.partition(":")
    ok = address in ("local", "auto") or (host and "/" not in rest and (
        (colon and _is_port(port_text)) or (not colon and address.startswith("ray://"))))
    if not ok:
        raise UsageError(f"--ray: expected 'local', 'auto', ray://HOST:PORT or HOST:PORT (a Ray cluster address), "
                         f"got {address!r}")


def _is_port(text: str) -> bool:
    try:
        port(text)
    except argparse.ArgumentTypeError:
        return False
    return True


def _check_checkpoints(option: str, run: str | Path) -> None:
    """The training state that ``--resume`` / ``--init-from`` loads opens as the zip archive torch writes: a
    truncated one (a copy cut short, a full disk) fails only after the learner was built, with torch's traceback."""
    import zipfile
    for name in ("state.pt", "buffer.pt"):
        path = Path(run) / "checkpoints" / name
        if not path.is_file():
            continue
        try:
            with zipfile.ZipFile(path):
                pass
        except (zipfile.BadZipFile, OSError) as exc:
            raise UsageError(f"{option}: {str(path)!r} is damaged (not a readable torch checkpoint: {exc}): give "
                             f"another run, or copy the checkpoint again") from None


def _check_distinct(option: str, patterns: list[str] | None) -> None:
    """No run or models folder is given twice (also as another spelling or through a glob): it would count twice
    in the mean and min-max over runs, or fill two rows of a cross-play matrix with the same team."""
    if not patterns:
        return
    from training.aggregate import expand_sources
    seen: dict[Path, str] = {}
    try:
        sources = expand_sources(patterns)
    except ValueError as exc:  # LearnedModelError: a glob that matches nothing
        raise UsageError(str(exc)) from None
    for source in sources:
        key = Path(source).resolve()
        if key in seen:
            raise UsageError(f"{option}: {source!r} is the same folder as {seen[key]!r}: give each run or models "
                             f"folder once")
        seen[key] = source


def check_config(args: argparse.Namespace) -> None:
    """The numbers that other modules' parsers take loosely (``RECHECKED``), sweep's ``--workers`` and ``--ray``,
    and ``--config`` (when the command reads it: an existing, non-empty file): else ``UsageError`` naming the
    option (the defaults, e.g. configs/role_based.toml, are relative to the repository root)."""
    import os
    try:
        for name, check in RECHECKED:
            recheck(args, name, check)
        if args.command == "sweep":
            recheck(args, "workers", int_in(1, max(2, os.cpu_count() or 1), "local processes, one per CPU"))
    except argparse.ArgumentTypeError as exc:
        raise UsageError(str(exc)) from None
    if getattr(args, "ray", None) is not None:
        _check_ray(args.ray)
    if args.command == "crossplay":
        _check_distinct("RUN_OR_MODELS", args.sources)
    if args.command == "evaluate":
        _check_distinct("--run/--models", (args.run or []) + (args.models or []))
    if args.command == "train":
        if args.init_from is not None:
            _check_checkpoints("--init-from", args.init_from)
        if args.resume:
            _check_checkpoints("--resume", args.out)
    path = getattr(args, "config", None)
    learned = getattr(args, "run", None) or getattr(args, "models", None)  # their own config is used
    if not isinstance(path, str) or getattr(args, "resume", False) or learned:
        return
    p = Path(path)
    if not p.exists() and path.strip():
        where = "" if p.is_absolute() else f" in {Path.cwd()} (the shipped configs are in the repository's configs/)"
        raise UsageError(f"--config: {path!r} does not exist{where}: give --config PATH")
    try:
        check_in_file(path)
    except argparse.ArgumentTypeError as exc:
        raise UsageError(f"--config: {exc}") from None
    if args.command != "sweep":
        from runtime.spec import load_toml
        if not load_toml(p):  # every key has a default: an empty file would run the defaults, silently
            raise UsageError(f"--config: {path!r} is empty (no name, [spec], [train] or [rewards]): give an "
                             f"experiment TOML, e.g. configs/role_based.toml")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        check_config(args)
        check_outputs(args)
        return int(args.func(args) or 0)
    except (SpecError, UsageError) as exc:
        print(f"swarm-train {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:  # a disk or permission failure after the checks: still one line, no traceback
        print(f"swarm-train {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"swarm-train {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
