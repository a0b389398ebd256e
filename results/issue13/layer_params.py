"""What the avoidance layer's parameters cost a team that pursues like the classical one: the classical team flown
through the layer (runtime.avoidance) with its default parameters, with a less conservative barrier, with the
teammate barrier planned at the pair's relative deceleration (teammate_braking) and, as a diagnostic, without the
teammate barrier, against each kind of the held-out suite (the same episodes: evaluation seed 0). Min distance [m] / tracking, captures and
team contacts per episode, and the suite mean.

    .venv/bin/python results/issue13/layer_params.py [CONFIG] [EPISODES] [VARIANT,...]
                                                        (configs/role_based.toml, 100, every variant)
"""
import dataclasses
import sys

import numpy as np

from runtime.avoidance import P_MATE_MARGIN, avoid_agents, avoid_rows, role_tables
from training.baselines import ClassicalPursuers, TeamPolicy
from training.config import ExperimentConfig
from training.evader_suite import SUITE, make_suite_evader
from training.evaluate import evaluate, mean_of

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100
nt = cfg.spec.team.n_team
OFF = -100.0
"""A teammate margin no spec accepts (it must be >= 0), set in the kernel's tables only: the teammate half-planes
then allow more than any speed, and the layer keeps only its walls, obstacles and reachability."""
VARIANTS = {  # name: AvoidanceSpec overrides (None: no layer)
    "no layer": None,
    "default": {},
    "braking 2.0": {"braking": 2.0},
    "braking 2.5": {"braking": 2.5},
    "braking 2.8": {"braking": 2.8},
    "teammate margin 0.05": {"teammate_margin": 0.05},
    "braking 2.5, margin 0.05": {"braking": 2.5, "teammate_margin": 0.05},
    "teammate barrier off": {"teammate_margin": OFF},  # a diagnostic only: which part of the layer costs
    "teammate braking 2.25": {"teammate_braking": 2.25},
    "teammate braking 3.0": {"teammate_braking": 3.0},
}
ONLY = sys.argv[3].split(",") if len(sys.argv) > 3 else list(VARIANTS)  # a subset, by name


class Layered:
    mates_off = False

    def __init__(self, spec):
        self.c, self.spec = ClassicalPursuers(), spec

    def act(self, obs, env):
        a = self.c.act(obs, env)
        if not self.mates_off:
            avoid_agents(self.spec, obs, a, np.arange(nt))
            return a
        for i in range(nt):  # the kernel on tables without the teammate barrier
            params, layout = role_tables(self.spec, self.spec.roles[i])
            params = params.copy()
            params[P_MATE_MARGIN] = OFF
            col = np.ascontiguousarray(a[:, i], dtype=np.float64)
            avoid_rows(obs[:, i], col, params, layout)
            a[:, i] = col
        return a


def fmt(m):
    return (f"{m['mean_min_dist']:.3f}/{m['tracking_rate']:.3f} cap {m['captures_per_episode']:5.2f} "
            f"tc {m['team_contacts_per_episode']:.2f} (mates {m['teammate_contacts_per_episode']:.2f}, "
            f"obstacles {m['team_obstacle_contacts_per_episode']:.2f})")


for name in ONLY:
    over = VARIANTS[name]
    if over is None:
        team = ClassicalPursuers()
    elif over.get("teammate_margin") == OFF:
        team = Layered(dataclasses.replace(cfg.spec, avoidance=dataclasses.replace(cfg.spec.avoidance, enabled=True)))
        team.mates_off = True
    else:
        av = dataclasses.replace(cfg.spec.avoidance, enabled=True, **over)
        team = Layered(dataclasses.replace(cfg.spec, avoidance=av))
    per = {kind: evaluate(cfg, TeamPolicy(team, make_suite_evader(kind, 0)), eps, seed=0, progress=False)
           for kind in SUITE}
    print(f"{name:26s} suite {fmt(mean_of(list(per.values())))}   "
          + "  ".join(f"{k} {v['mean_min_dist']:.3f}/{v['tracking_rate']:.3f}" for k, v in per.items()), flush=True)
