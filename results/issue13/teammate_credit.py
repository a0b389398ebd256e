"""The DAgger teacher (the classical team with push 1) flown through the config's avoidance layer with
``spec.avoidance.teammate_credit`` set to each CREDIT (the share of a teammate's own speed away added to the approach
budget toward it), beside the config's own layer, against every held-out suite kind (evaluation seed 0, the
evaluator's episodes). Min distance [m] / tracking and team contacts per episode.

    cd results/issue13 && ../../.venv/bin/python teammate_credit.py CONFIG EPISODES CREDIT ...
"""
import dataclasses
import sys

from _layered import LayeredClassical, print_suite_line
from training.config import ExperimentConfig

if len(sys.argv) < 4:
    sys.exit(__doc__)
cfg = ExperimentConfig.from_toml(sys.argv[1])
eps = int(sys.argv[2])
print(f"{cfg.name}: avoidance {cfg.spec.avoidance}")
print_suite_line(cfg, "teacher (push 1), the config's layer", lambda: LayeredClassical(cfg.spec, 1.0), eps)
for arg in sys.argv[3:]:
    spec = dataclasses.replace(cfg.spec, avoidance=dataclasses.replace(cfg.spec.avoidance, teammate_credit=float(arg)))
    run = dataclasses.replace(cfg, spec=spec)
    print_suite_line(run, f"teacher (push 1), teammate_credit {arg}", lambda: LayeredClassical(spec, 1.0), eps)
