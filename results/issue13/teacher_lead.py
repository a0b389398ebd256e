"""The DAgger teacher with a different look-ahead: would a teacher that leads the evaders longer or shorter than
the classical team (``ClassicalPursuers.lead_time_max``, 0.6 s) be a stronger teacher on the held-out kinds? The
shipped recipe's teacher (push ``train.teacher_separation_gain``) flown through the config's avoidance layer, 100
episodes per suite kind (evaluation seed 0: the same episodes as teacher_reach.py); min distance [m] / tracking and
team contacts per episode; the classical team itself (no layer, push 3, lead 0.6 s) first, as the bar.

    .venv/bin/python results/issue13/teacher_lead.py [CONFIG] [EPISODES] [LEAD ...]   (configs/role_based.toml, 100,
                                                                                          0.6 0.3 1.0 1.5)
"""
import sys

from _layered import LayeredClassical
from training.baselines import ClassicalPursuers, TeamPolicy
from training.config import ExperimentConfig
from training.evader_suite import SUITE, make_suite_evader
from training.evaluate import evaluate, mean_of

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100
leads = [float(x) for x in sys.argv[3:]] or [0.6, 0.3, 1.0, 1.5]


def report(label: str, make) -> None:
    per = {kind: evaluate(cfg, TeamPolicy(make(), make_suite_evader(kind, 0)), eps, seed=0, progress=False)
           for kind in SUITE}
    m = mean_of(list(per.values()))
    print(f"{label}: suite {m['mean_min_dist']:.3f}/{m['tracking_rate']:.3f} tc {m['team_contacts_per_episode']:.2f}   "
          + "  ".join(f"{k} {v['mean_min_dist']:.3f}/{v['tracking_rate']:.3f}" for k, v in per.items()), flush=True)


print(f"{cfg.name}: avoidance {cfg.spec.avoidance}")
report("classical team (lead 0.6 s, push 3, no layer)", ClassicalPursuers)
for lead in leads:
    def make(lead=lead):
        t = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain)
        t.c.lead_time_max = lead
        return t
    report(f"teacher, lead {lead:g} s", make)
