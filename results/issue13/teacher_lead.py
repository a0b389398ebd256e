"""The DAgger teacher with a different look-ahead: would a teacher that leads the evaders longer or shorter than
the classical team (``ClassicalPursuers.lead_time_max``, 0.6 s) be a stronger teacher on the held-out kinds? The
shipped recipe's teacher (push ``train.teacher_separation_gain``) flown through the config's avoidance layer, 100
episodes per suite kind (evaluation seed 0: the same episodes as teacher_reach.py); min distance [m] / tracking and
team contacts per episode; the classical team itself (no layer, push 3, lead 0.6 s) first, as the bar.

    .venv/bin/python results/issue13/teacher_lead.py [CONFIG] [EPISODES] [LEAD ...]   (configs/role_based.toml, 100,
                                                                                          0.6 0.3 1.0 1.5)
    .venv/bin/python results/issue13/teacher_lead.py ... --seeds 100,101

``--seeds``: other evaluation seeds, their episodes pooled, and the scripted fleeing evaders added, four decimals:
validation episodes to choose a teacher on, kept apart from the evaluation seeds that report results (0, 1, 2).
"""
import sys

from _layered import VALIDATION, LayeredClassical, print_suite_line
from training.baselines import ClassicalPursuers
from training.config import ExperimentConfig

args = sys.argv[1:]
seeds, extra = (0,), {}
if "--seeds" in args:
    i = args.index("--seeds")
    try:
        seeds = tuple(int(x) for x in args[i + 1].split(","))
    except (IndexError, ValueError):
        sys.exit("teacher_lead.py: --seeds takes comma-separated integers, e.g. --seeds 100,101")
    del args[i:i + 2]
    extra = {**VALIDATION, "seeds": seeds}
cfg = ExperimentConfig.from_toml(args[0] if args else "configs/role_based.toml")
eps = int(args[1]) if len(args) > 1 else 100
leads = [float(x) for x in args[2:]] or [0.6, 0.3, 1.0, 1.5]


print(f"{cfg.name}: avoidance {cfg.spec.avoidance}" + (f"; evaluation seeds {seeds} pooled" if extra else ""))
print_suite_line(cfg, "classical team (lead 0.6 s, push 3, no layer)", ClassicalPursuers, eps, **extra)
for lead in leads:
    def make(lead=lead):
        t = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain)
        t.c.lead_time_max = lead
        return t
    print_suite_line(cfg, f"teacher, lead {lead:g} s", make, eps, **extra)
