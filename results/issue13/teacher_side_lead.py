"""A teacher whose look-ahead shortens when its target runs off the line of sight: a target running sideways to its
pursuer (as the juker does, zig-zagging about its flee direction) is likely to turn back, so lead it less. Each
pursuer leads ``lead_time_max`` (0.6 s) while the target's velocity points along the bearing from the pursuer to it,
and down to ``SIDE`` s as the angle between them grows to ``ANGLE`` degrees (linear in the cosine; beyond it, and
toward the pursuer, ``SIDE``). Everything the teacher reads is in a pursuer's own observation (the target's offset and
velocity), so a feed-forward student could learn it (``ClassicalPursuers.lead_side_time``, ``lead_side_angle``;
``train.teacher_side_lead``, ``teacher_side_angle``). The shipped recipe's teacher (push
``train.teacher_separation_gain``) flown through the config's avoidance layer, on validation episodes (evaluation
seeds 100 and 101 pooled, 200 episodes each per kind, the scripted fleeing evaders added). See results/README.md,
twenty-eighth attempt. (The output files were written by this script's first form, a subclass of ClassicalPursuers
with the same rule, before the option existed; its actions equal the option's to the bit on random states.)

    cd results/issue13 && ../../.venv/bin/python teacher_side_lead.py CONFIG SIDE@ANGLE [SIDE@ANGLE ...]
"""
import sys

from _layered import VALIDATION, LayeredClassical, print_suite_line, print_validation_bars
from training.config import ExperimentConfig


cfg = ExperimentConfig.from_toml(sys.argv[1])
print_validation_bars(cfg)
for arg in sys.argv[2:]:
    side, angle = (float(x) for x in arg.split("@"))

    def make(side=side, angle=angle):
        t = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain)
        t.c.lead_side_time, t.c.lead_side_angle = side, angle
        return t
    print_suite_line(cfg, f"teacher, lead 0.6 s along the line of sight, {side:g} s from {angle:g} deg off it", make,
                     200, **VALIDATION)
