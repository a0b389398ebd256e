"""Headline figures over several training runs: mean and min-max per metric, the classical team beside them.

``swarm-train evaluate --run A --run B --run C --evader ...`` (or ``--run 'runs/rb_s*'``, or several
``--models``) evaluates every run against every evader kind on the same evaluation seeds, and the classical
pursuer team against the same evaders: once per kind for scripted evaders (they are the same for every run),
once per run for each run's co-trained evaders (then aggregated like the runs). The Markdown output is the
table ``results/README.md`` shows: a row per evader kind, the learned teams' mean with min-max over runs
beside the classical team, the split collision counts, on how many runs the learned team was as close and
tracked as often as the classical one (min distance <= and tracking rate >=), and on how many its own
contacts (teammate + team-obstacle) per episode were at most the classical team's.
"""
from __future__ import annotations

import glob
import json
import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from training.baselines import ClassicalPursuers, TeamPolicy
from training.evader_spec import SUITE_MEAN, expand, label, make_evaders
from training.evaluate import EVAL_SEED_OFFSET, evaluate, mean_of, write_text_atomic
from training.learned_eval import LearnedModelError, load_sources, team

log = logging.getLogger(__name__)

HEADLINE = (("mean_min_dist", "min dist [m]"), ("tracking_rate", "tracking"), ("coverage", "coverage"),
            ("teammate_contacts_per_episode", "teammate contacts/ep"),
            ("team_obstacle_contacts_per_episode", "team-obstacle contacts/ep"),
            ("evader_contacts_per_episode", "evader-side contacts/ep"), ("captures_per_episode", "captures/ep"))
"""The metrics of the headline table, with their column names."""


def expand_sources(patterns: Sequence[str]) -> list[str]:
    """Run or models folders from paths and quoted globs (sorted matches); a glob that matches nothing is an
    error naming it."""
    out: list[str] = []
    for pat in patterns:
        if any(ch in pat for ch in "*?["):
            hits = sorted(h for h in glob.glob(pat) if Path(h).is_dir())
            if not hits:
                raise LearnedModelError(f"--run/--models {pat!r} matches no folder: check the pattern")
            out += hits
        else:
            out.append(pat)
    return out


def spread(docs: Sequence[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """``{"mean": ..., "min": ..., "max": ...}`` over evaluations, per metric of ``HEADLINE`` and a few more."""
    keys = [k for k in docs[0] if isinstance(docs[0][k], (int, float)) and not isinstance(docs[0][k], bool)]
    vals = {k: np.array([float(d[k]) for d in docs]) for k in keys if all(k in d for d in docs)}
    return {stat: {k: float(getattr(np, stat)(v)) for k, v in vals.items()} for stat in ("mean", "min", "max")}


def evaluate_runs(sources: Sequence[str], kinds: list[str], episodes: int, seed: int, n_envs: int,
                  classical: bool = True, progress: bool = True) -> dict[str, Any]:
    """Every source against every kind; per kind: ``runs`` (one metrics dict per source), ``mean``/``min``/
    ``max`` over them and ``classical`` (metrics, or per-run metrics and their spread for learned evaders)."""
    loaded = load_sources(sources, "aggregate runs of one configuration (different seeds) only")
    cfg = loaded[0][0]
    per_kind: dict[str, dict[str, Any]] = {}
    for kind in kinds:
        name = label(kind)
        runs = [evaluate(c, team(pol, kind, seed), episodes, seed=seed, n_envs=n_envs, progress=progress,
                         desc=f"{Path(src).parent.name} vs {name}") for c, pol, src in loaded]
        entry: dict[str, Any] = {"runs": runs, **spread(runs)}
        if classical and kind == "learned":
            cl = [evaluate(c, TeamPolicy(ClassicalPursuers(), pol), episodes, seed=seed, n_envs=n_envs,
                           progress=progress, desc=f"classical vs {Path(src).parent.name}")
                  for c, pol, src in loaded]
            entry["classical"] = {"runs": cl, **spread(cl)}
        elif classical:
            entry["classical"] = evaluate(cfg, TeamPolicy(ClassicalPursuers(), make_evaders(kind, seed)), episodes,
                                          seed=seed, n_envs=n_envs, progress=progress, desc=f"classical vs {name}")
        per_kind[name] = entry
    suite = [label(k) for k in kinds if k.startswith("suite:")]
    if len(suite) > 1:  # each run's suite mean, then the spread of those
        runs = [mean_of([per_kind[k]["runs"][i] for k in suite]) for i in range(len(loaded))]
        entry = {"runs": runs, **spread(runs), "kinds": suite}
        if classical:
            entry["classical"] = mean_of([per_kind[k]["classical"] for k in suite])
        per_kind[SUITE_MEAN] = entry
    return {"config": cfg.name, "spec_hash": cfg.spec.hash, "sources": list(sources),
            "files": [src for _, _, src in loaded],
            "episodes": episodes, "seed": seed, "n_envs": n_envs, "eval_seed_offset": EVAL_SEED_OFFSET,
            "evaders": per_kind}


def _classical_value(entry: dict[str, Any], key: str) -> tuple[float, list[float]] | None:
    """(the classical figure shown, its per-run values to compare against)."""
    cl = entry.get("classical")
    if cl is None:
        return None
    if "runs" in cl:
        return cl["mean"][key], [r[key] for r in cl["runs"]]
    return cl[key], [cl[key]] * len(entry["runs"])


def wins(entry: dict[str, Any]) -> int | None:
    """Runs whose team is at least as close (min distance) and tracks at least as often as the classical
    team on the same evaders."""
    md, tr = _classical_value(entry, "mean_min_dist"), _classical_value(entry, "tracking_rate")
    if md is None or tr is None:
        return None
    return sum(r["mean_min_dist"] <= m and r["tracking_rate"] >= t
               for r, m, t in zip(entry["runs"], md[1], tr[1]))


def fewer_contacts(entry: dict[str, Any]) -> int | None:
    """Runs whose team has at most the classical team's own contacts (teammate + team-obstacle) per episode."""
    cl = _classical_value(entry, "team_contacts_per_episode")
    if cl is None:
        return None
    return sum(r["team_contacts_per_episode"] <= c for r, c in zip(entry["runs"], cl[1]))


def markdown(doc: dict[str, Any]) -> str:
    """The headline table (a row per evader kind) and the per-run table, ready to paste."""
    n = len(doc["sources"])
    lines = [f"{doc['config']}: {n} runs ({', '.join(f'`{s}`' for s in doc['sources'])}), {doc['episodes']} "
             f"held-out episodes per run and evader kind (evaluation seed {doc['seed']}, seed offset "
             f"{doc['eval_seed_offset']}). Learned: mean [min-max] over runs; classical: the centralized "
             f"classical team on the same evaders and seeds.", ""]
    head = ["evaders"]
    for _, name in HEADLINE:
        head += [f"{name} learned", "classical"]
    head += [f"learned as close and tracking as often (runs of {n})",
             f"learned team contacts <= classical (runs of {n})"]
    lines += ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for kind, e in doc["evaders"].items():
        row = ["suite mean" if kind == SUITE_MEAN else kind]
        for key, _ in HEADLINE:
            fmt = "{:.2f}" if key.endswith("per_episode") else "{:.3f}"
            row.append(f"{fmt.format(e['mean'][key])} [{fmt.format(e['min'][key])}-{fmt.format(e['max'][key])}]")
            cl = _classical_value(e, key)
            row.append("" if cl is None else fmt.format(cl[0]))
        for count in (wins(e), fewer_contacts(e)):
            row.append("" if count is None else f"{count}/{n}")
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "Per run: min dist [m] / tracking rate", ""]
    kinds = list(doc["evaders"])
    lines += ["| run | " + " | ".join("suite mean" if k == SUITE_MEAN else k for k in kinds) + " |",
              "|---" * (len(kinds) + 1) + "|"]
    for i, src in enumerate(doc["sources"]):
        cells = [f"{doc['evaders'][k]['runs'][i]['mean_min_dist']:.3f} / "
                 f"{doc['evaders'][k]['runs'][i]['tracking_rate']:.3f}" for k in kinds]
        lines.append(f"| `{src}` | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def cmd_evaluate_runs(args: Any) -> int:
    from training.cli import UsageError
    sources = expand_sources([*(args.run or []), *(args.models or [])])
    kinds = expand(args.evader or "learned")
    doc = evaluate_runs(sources, kinds, args.episodes, args.seed, args.n_envs, classical=not args.no_classical,
                        progress=not args.no_progress)
    text = markdown(doc)
    print(text, end="")
    try:
        if args.json:
            write_text_atomic(args.json, json.dumps(doc, indent=2, sort_keys=True) + "\n")
            print(f"wrote {args.json}")
        if args.md:
            write_text_atomic(args.md, text)
            print(f"wrote {args.md}")
    except OSError as exc:
        raise UsageError(f"cannot write the output: {exc}") from None
    return 0
