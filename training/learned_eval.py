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
    p.add_argument("--evader", choices=EVADER_KINDS, default="learned",
                   help="with --run/--models: the co-trained evader actors ('learned', default) or the scripted "
                        "fleeing evaders ('scripted')")
    p.add_argument("--no-classical", action="store_true",
                   help="with --run/--models: skip the classical pursuer team's column")


def cmd_evaluate_learned(args: Any) -> int:
    import json

    from training.cli import UsageError
    from training.evaluate import PAPER, format_table
    from training.checkpoint import CheckpointError
    try:
        res = evaluate_learned(args.run, args.models, args.evader, args.episodes, args.seed, args.n_envs,
                               classical=not args.no_classical, progress=not args.no_progress)
    except (LearnedModelError, CheckpointError, OSError) as exc:
        raise UsageError(str(exc)) from None
    except ValueError as exc:  # runtime.policy.PolicyError and spec errors
        raise UsageError(str(exc)) from None
    cols = {f"ours vs {args.evader}": res}
    if "classical" in res:
        cols[f"classical vs {args.evader}"] = res["classical"]
    print(f"{res['config']}: {res['source']} vs {args.evader} evaders, {res['episodes']} episodes, "
          f"seed {args.seed}, {res['wall_s']:.1f} s")
    print(format_table(cols, PAPER.get(res["config"])))
    if args.json:
        p = Path(args.json)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps(res, indent=2, sort_keys=True) + "\n")
        print(f"wrote {args.json}")
    return 0
