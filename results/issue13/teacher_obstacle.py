"""The DAgger teacher with a continuous slide along obstacles: is a teacher whose label does not flip side when its
wish points straight at an obstacle's centre (``ClassicalPursuers.obstacle_side_softness``,
``train.teacher_obstacle_softness``) as strong as the shipped one? The shipped recipe's teacher (push
``train.teacher_separation_gain``), flown through the config's avoidance layer, with softness 0 (the classical
team's hard side choice), 0.1 and 0.3; 100 episodes per suite kind (evaluation seed 0: the same episodes as
teacher_reach.py and the screens); min distance [m] / tracking and team contacts per episode.

    .venv/bin/python results/issue13/teacher_obstacle.py [CONFIG] [EPISODES]   (configs/role_based.toml, 100)
"""
import sys

from _layered import LayeredClassical
from training.baselines import TeamPolicy
from training.config import ExperimentConfig
from training.evader_suite import SUITE, make_suite_evader
from training.evaluate import evaluate, mean_of

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100


def teacher(softness: float, kind: str) -> TeamPolicy:
    layered = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain)
    layered.c.obstacle_side_softness = softness
    return TeamPolicy(layered, make_suite_evader(kind, 0))


print(f"{cfg.name}: teacher push {cfg.train.teacher_separation_gain:g}, avoidance {cfg.spec.avoidance}")
for softness in (0.0, 0.1, 0.3):
    per = {kind: evaluate(cfg, teacher(softness, kind), eps, seed=0, progress=False) for kind in SUITE}
    m = mean_of(list(per.values()))
    print(f"softness {softness:g}: suite {m['mean_min_dist']:.3f}/{m['tracking_rate']:.3f} tc "
          f"{m['team_contacts_per_episode']:.2f}   "
          + "  ".join(f"{k} {v['mean_min_dist']:.3f}/{v['tracking_rate']:.3f}" for k, v in per.items()), flush=True)
