"""The DAgger teacher against the held-out suite: the classical team with the teammate push the recipe's teacher
uses (``train.teacher_separation_gain``) and with the classical team's own, each flown through the config's
avoidance layer, 100 episodes per suite kind (evaluation seed 0: the same episodes as the screens). What a student
that cloned its teacher exactly would get; min distance [m] / tracking and team contacts per episode.

    .venv/bin/python results/issue13/teacher_layer.py [CONFIG] [EPISODES]   (configs/role_based.toml, 100)
"""
import sys

from _layered import LayeredClassical
from training.baselines import ClassicalPursuers, TeamPolicy
from training.config import ExperimentConfig
from training.evader_suite import SUITE, make_suite_evader
from training.evaluate import evaluate, mean_of

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100

print(f"{cfg.name}: avoidance {cfg.spec.avoidance}")
for push in sorted({cfg.train.teacher_separation_gain, ClassicalPursuers.separation_gain}):
    per = {kind: evaluate(cfg, TeamPolicy(LayeredClassical(cfg.spec, push), make_suite_evader(kind, 0)), eps, seed=0,
                          progress=False) for kind in SUITE}
    m = mean_of(list(per.values()))
    print(f"push {push:g}: suite {m['mean_min_dist']:.3f}/{m['tracking_rate']:.3f} tc "
          f"{m['team_contacts_per_episode']:.2f}   "
          + "  ".join(f"{k} {v['mean_min_dist']:.3f}/{v['tracking_rate']:.3f}" for k, v in per.items()), flush=True)
