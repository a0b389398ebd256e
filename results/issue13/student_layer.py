"""A trained team flown through another avoidance layer than the one it was trained with (a probe, not a recipe:
the actors stay the same): which of the layer's parameters cost the learned team distance or tracking against the
held-out kinds, and whether the team then touches anything. Min distance [m] / tracking and team contacts per
episode (teammate + team-obstacle), per run, beside the classical team on the same episodes (evaluation seed 0).

    .venv/bin/python results/issue13/student_layer.py EPISODES KINDS RUN [RUN ...] -- FIELD=VALUE[,FIELD=VALUE] ...

KINDS: comma-separated suite kinds (e.g. perimeter,juker); each argument after ``--`` is one layer variant, its
fields those of ``[spec.avoidance]`` (``default`` flies the run's own layer).
"""
import dataclasses
import sys

from training.learned_eval import evaluate_kind, load_source

args = sys.argv[1:]
cut = args.index("--")
episodes, kinds, runs, variants = int(args[0]), args[1].split(","), args[2:cut], args[cut + 1:]


def variant(spec, text):
    if text == "default":
        return spec
    fields = {}
    for item in text.split(","):
        k, v = item.split("=")
        fields[k] = float(v)
    return dataclasses.replace(spec, avoidance=dataclasses.replace(spec.avoidance, **fields))


for run in runs:
    cfg, learned, _ = load_source(run)
    for text in variants:
        spec = variant(cfg.spec, text)
        c = dataclasses.replace(cfg, spec=spec)
        learned.spec = spec
        line = []
        for kind in kinds:
            r = evaluate_kind(c, learned, f"suite:{kind}", episodes, 0, 50, True, False)
            tc = r["team_contacts_per_episode"]
            k = r["classical"]
            line.append(f"{kind} {r['mean_min_dist']:.4f}/{r['tracking_rate']:.4f} tc {tc:.2f} "
                        f"(classical {k['mean_min_dist']:.4f}/{k['tracking_rate']:.4f})")
        print(f"{run} [{text}]  " + "  ".join(line), flush=True)
