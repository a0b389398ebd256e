"""What the avoidance layer's parameters cost a team that pursues like the classical one: the classical team flown
through the layer (runtime.avoidance) with its default parameters, with a less conservative barrier, with the
teammate barrier planned at the pair's relative deceleration (teammate_braking) and, as a diagnostic, without the
teammate barrier, against each kind of the held-out suite (the same episodes: evaluation seed 0). Min distance [m] /
tracking, captures and team contacts per episode, and the suite mean.

    .venv/bin/python results/issue13/layer_params.py [CONFIG] [EPISODES] [VARIANT,...]
                                                        (configs/role_based.toml, 100, every variant)
"""
import dataclasses
import sys

from _layered import LayeredClassical
from runtime.avoidance import P_MATE_MARGIN
from training.baselines import ClassicalPursuers, TeamPolicy
from training.config import ExperimentConfig
from training.evader_suite import SUITE, make_suite_evader
from training.evaluate import evaluate, mean_of

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100


def without_teammates(params, layout):
    """The kernel's tables with a teammate margin no spec accepts (it must be >= 0): the teammate half-planes then
    allow more than any speed, and the layer keeps only its walls, obstacles and reachability."""
    params = params.copy()
    params[P_MATE_MARGIN] = -100.0
    return params, layout


VARIANTS = {  # name: AvoidanceSpec overrides (None: no layer)
    "no layer": None,
    "default": {},
    "braking 2.0": {"braking": 2.0},
    "braking 2.5": {"braking": 2.5},
    "braking 2.8": {"braking": 2.8},
    "teammate margin 0.05": {"teammate_margin": 0.05},
    "braking 2.5, margin 0.05": {"braking": 2.5, "teammate_margin": 0.05},
    "teammate barrier off": {},  # with DIAGNOSTICS' tables
    "teammate braking 2.25": {"teammate_braking": 2.25},
    "teammate braking 3.0": {"teammate_braking": 3.0},
    "teammate braking 4.5": {"teammate_braking": 4.5},
    "braking 2.0 + mates 3.0": {"braking": 2.0, "teammate_braking": 3.0},
    "braking 2.0 + mates 4.0": {"braking": 2.0, "teammate_braking": 4.0},
}
DIAGNOSTICS = {"teammate barrier off": without_teammates}  # which part of the layer costs
ONLY = sys.argv[3].split(",") if len(sys.argv) > 3 else list(VARIANTS)  # a subset, by name


def fmt(m):
    return (f"{m['mean_min_dist']:.3f}/{m['tracking_rate']:.3f} cap {m['captures_per_episode']:5.2f} "
            f"tc {m['team_contacts_per_episode']:.2f} (mates {m['teammate_contacts_per_episode']:.2f}, "
            f"obstacles {m['team_obstacle_contacts_per_episode']:.2f})")


for name in ONLY:
    over = VARIANTS[name]
    if over is None:
        team = ClassicalPursuers()
    else:
        av = dataclasses.replace(cfg.spec.avoidance, enabled=True, **over)
        team = LayeredClassical(dataclasses.replace(cfg.spec, avoidance=av), tables=DIAGNOSTICS.get(name))
    per = {kind: evaluate(cfg, TeamPolicy(team, make_suite_evader(kind, 0)), eps, seed=0, progress=False)
           for kind in SUITE}
    print(f"{name:26s} suite {fmt(mean_of(list(per.values())))}   "
          + "  ".join(f"{k} {v['mean_min_dist']:.3f}/{v['tracking_rate']:.3f}" for k, v in per.items()), flush=True)
