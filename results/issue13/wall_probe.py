"""Is the avoidance layer's wall barrier what keeps the students off the perimeter runner? The shipped recipe's
DAgger teacher (push ``train.teacher_separation_gain``) through the config's layer, with the layer's walls moved
0, 0.1 and 0.2 m out (the kernel's ``P_HALF_WIDTH``; the world's walls stay where they are), against the held-out
perimeter runner, juker and hider, 100 episodes per kind (evaluation seed 0: the same episodes as teacher_lead.py);
min distance [m] / tracking and team contacts per episode.

    .venv/bin/python results/issue13/wall_probe.py [CONFIG] [EPISODES]   (configs/role_based.toml, 100)
"""
import sys

from _layered import LayeredClassical
from runtime.avoidance import P_HALF_WIDTH
from training.baselines import TeamPolicy
from training.config import ExperimentConfig
from training.evader_suite import make_suite_evader
from training.evaluate import evaluate

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100

for d in [0.0, 0.1, 0.2]:
    def tables(params, layout, d=d):
        params = params.copy()
        params[P_HALF_WIDTH] += d
        return params, layout
    out = []
    for kind in ["perimeter", "juker", "hider"]:
        team = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain, tables)
        m = evaluate(cfg, TeamPolicy(team, make_suite_evader(kind, 0)), eps, seed=0, progress=False)
        out.append(f"{kind} {m['mean_min_dist']:.3f}/{m['tracking_rate']:.3f} tc {m['team_contacts_per_episode']:.2f}")
    print(f"walls moved out {d:g} m: " + "  ".join(out), flush=True)
