"""The DAgger teacher with another teammate push (and look-ahead): the classical team with push ``P`` (and lead
``L`` s) flown through the config's avoidance layer, against every held-out suite kind (evaluation seed 0: the
same episodes as ``swarm-train evaluate --seed 0``); the classical team itself (no layer, push 3, lead 0.6 s) first,
as the bar. Min distance [m] / tracking and team contacts per episode.

    .venv/bin/python results/issue13/teacher_push.py CONFIG EPISODES P[@L] ...     (e.g. configs/multi_target.toml
                                                                                  200 1 1.5 2 3 2@0.4)
"""
import sys

from _layered import LayeredClassical, print_suite_line
from training.baselines import ClassicalPursuers
from training.config import ExperimentConfig

if len(sys.argv) < 4:
    sys.exit(__doc__)
cfg = ExperimentConfig.from_toml(sys.argv[1])
eps = int(sys.argv[2])
print(f"{cfg.name}: avoidance {cfg.spec.avoidance}")
print_suite_line(cfg, "classical team (lead 0.6 s, push 3, no layer)", ClassicalPursuers, eps)
for arg in sys.argv[3:]:
    push, _, lead = arg.partition("@")
    def make(push=float(push), lead=float(lead or ClassicalPursuers.lead_time_max)):
        t = LayeredClassical(cfg.spec, push)
        t.c.lead_time_max = lead
        return t
    print_suite_line(cfg, f"teacher, push {push}, lead {lead or '0.6'} s", make, eps)
