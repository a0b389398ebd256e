"""The DAgger teacher with a shorter teammate push: would a teacher whose label next to a crowded target is more
nearly its pursuit wish (the push reaching 0.3 or 0.25 m instead of 0.5, or no push at all) be a better teacher?
The classical team with push 1 (the shipped recipe's teacher), each variant flown through the config's avoidance
layer, 100 episodes per suite kind (evaluation seed 0: the same episodes as teacher_layer.py and the screens); min
distance [m] / tracking and team contacts per episode.

    .venv/bin/python results/issue13/teacher_reach.py [CONFIG] [EPISODES]   (configs/role_based.toml, 100)
"""
import sys

from _layered import LayeredClassical
from training.baselines import TeamPolicy
from training.config import ExperimentConfig
from training.evader_suite import SUITE, make_suite_evader
from training.evaluate import evaluate, mean_of

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100


def teacher(push: float, reach: float, kind: str) -> TeamPolicy:
    layered = LayeredClassical(cfg.spec, push)
    layered.c.separation_reach = reach
    return TeamPolicy(layered, make_suite_evader(kind, 0))


print(f"{cfg.name}: avoidance {cfg.spec.avoidance}")
for push, reach in [(cfg.train.teacher_separation_gain, 0.5), (cfg.train.teacher_separation_gain, 0.3),
                    (cfg.train.teacher_separation_gain, 0.25), (0.0, 0.5)]:
    per = {kind: evaluate(cfg, teacher(push, reach, kind), eps, seed=0, progress=False) for kind in SUITE}
    m = mean_of(list(per.values()))
    print(f"push {push:g} reach {reach:g}: suite {m['mean_min_dist']:.3f}/{m['tracking_rate']:.3f} tc "
          f"{m['team_contacts_per_episode']:.2f}   "
          + "  ".join(f"{k} {v['mean_min_dist']:.3f}/{v['tracking_rate']:.3f}" for k, v in per.items()), flush=True)
