"""The fair bar for partial observability: the classical team flown on each pursuer's own observation
(``ClassicalPursuers.information = "observed"``: the targets as the drone knows them, by its own sensing within 0.5 m or
relayed by teammates within 2 m, carried forward by the sighting's age; the team's split from the observation's
``assigned`` field; Lloyd's step while it knows no target; scouts as in the classical team), beside the full-state
classical team and the learned partial-observability team, on the same evaders and episodes as `swarm-train evaluate
--run RUN --evader all --episodes 200 --seed 0` (evaluation seed 0, 50 envs a round).

    .venv/bin/python results/issue13/classical_partial.py runs/rb_v26_partial_s0 runs/rb_v26_partial_s1 \\
        runs/rb_v26_partial_s2 [--episodes 200] [--seed 0] [--json results/issue13/classical_partial.json]

The learned team's and the full-state classical team's figures are evaluated here too (the same as that command's).
"""
import argparse
import json

import numpy as np

from training.baselines import ClassicalPursuers, TeamPolicy
from training.evader_spec import expand, label, make_evaders
from training.evaluate import evaluate
from training.learned_eval import evaluate_kind, load_source

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("runs", nargs="+", help="run folders of a partial-observability config")
p.add_argument("--episodes", type=int, default=200)
p.add_argument("--seed", type=int, default=0)
p.add_argument("--json", default=None, help="also write every figure here")
args = p.parse_args()

observed = ClassicalPursuers()
observed.information = "observed"
sources = [load_source(run) for run in args.runs]
for run, (cfg, _, _) in zip(args.runs, sources):
    if cfg.spec.sensing.observability != "partial":
        p.error(f"{run}: its spec has sensing.observability = {cfg.spec.sensing.observability!r}; give runs of a "
                "partial-observability config")
TEAMS = ("learned", "classical_observed", "classical")
out: dict = {"episodes": args.episodes, "seed": args.seed, "runs": args.runs, "kinds": {}}
print(f"{args.episodes} held-out episodes per kind and run, evaluation seed {args.seed}; min dist [m] / tracking; "
      "mean over the runs (the scripted kinds are the same episodes for every run)")
print(f"{'evaders':11s} {'learned, partial':18s} {'classical, own observation':28s} {'classical, full state':22s}")
for kind in expand("all"):
    rows, shared = [], None  # the classical teams against scripted evaders: the same episodes for every run
    for cfg, learned, _ in sources:
        res = evaluate_kind(cfg, learned, kind, args.episodes, args.seed, n_envs=50, classical=shared is None,
                            progress=False)
        if shared is None:
            res["classical_observed"] = evaluate(cfg, TeamPolicy(observed, make_evaders(kind, args.seed, learned)),
                                                 args.episodes, seed=args.seed, n_envs=50, progress=False)
            if kind != "learned":
                shared = {k: res[k] for k in TEAMS[1:]}
        else:
            res.update(shared)
        rows.append(res)
    fig = {k: tuple(float(np.mean([(r if k == "learned" else r[k])[m] for r in rows]))
                    for m in ("mean_min_dist", "tracking_rate")) for k in TEAMS}
    out["kinds"][label(kind)] = {"per_run": rows, "mean": fig}
    cell = {k: f"{d:.3f} / {t:.3f}" for k, (d, t) in fig.items()}
    print(f"{label(kind):11s} {cell['learned']:18s} {cell['classical_observed']:28s} {cell['classical']:22s}", flush=True)
suite = [label(k) for k in expand("all") if k.startswith("suite:")]
mean = {k: tuple(float(np.mean([out["kinds"][s]["mean"][k][i] for s in suite])) for i in (0, 1)) for k in TEAMS}
out["suite_mean"] = mean
cell = {k: f"{d:.3f} / {t:.3f}" for k, (d, t) in mean.items()}
print(f"{'suite mean':11s} {cell['learned']:18s} {cell['classical_observed']:28s} {cell['classical']:22s}")
if args.json:
    with open(args.json, "w") as fh:
        json.dump(out, fh, indent=1, default=float)
    print(f"wrote {args.json}")
