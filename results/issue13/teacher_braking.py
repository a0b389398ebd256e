"""The avoidance layer's wall and obstacle barrier, at the teacher: the thirty-second attempt's probe. Flown through
the layer, the classical team is 0.011 m farther from the perimeter runner than without it (``layer_params.txt``:
planned at 1.5 m/s^2, role_based's layer of the time), and the perimeter runner is where multi_target's students
give back their margin. Here the shipped recipe's teacher (push ``train.teacher_separation_gain``) flies through the
config's layer with the barrier planned at each deceleration given (``spec.avoidance.braking``), the teammate
barrier either kept where it is (``teammate_braking`` set to what it is now: ``BRAKING`` alone) or moved with it
(``BRAKING@both``: a spec whose ``teammate_braking`` is 0 plans the teammate barrier at ``braking`` too), on the
validation episodes (evaluation seeds 100 and 101 pooled, 200 episodes each per kind, the scripted fleeing evaders
added); the classical team first, as the bar. See results/README.md, thirty-second attempt.

    cd results/issue13 && ../../.venv/bin/python teacher_braking.py CONFIG BRAKING[@both] [...]
"""
import dataclasses
import sys

from _layered import VALIDATION, LayeredClassical, print_suite_line, print_validation_bars
from training.config import ExperimentConfig

cfg = ExperimentConfig.from_toml(sys.argv[1])
av = cfg.spec.avoidance
print_validation_bars(cfg)
for arg in sys.argv[2:]:
    braking, _, both = arg.partition("@")
    mates = av.teammate_braking if both else (av.teammate_braking or av.braking)
    layer = dataclasses.replace(av, braking=float(braking), teammate_braking=mates)
    spec = dataclasses.replace(cfg.spec, avoidance=layer)
    print_suite_line(cfg, f"teacher, barrier at {float(braking):g} m/s^2, teammate barrier at "
                     f"{layer.teammate_braking or layer.braking:g}", lambda: LayeredClassical(spec,
                     cfg.train.teacher_separation_gain), 200, **VALIDATION)
