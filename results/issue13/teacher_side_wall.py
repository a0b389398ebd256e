"""The side lead away from the walls: the twenty-eighth attempt's side lead (0.6 s along the line of sight, ``SIDE``
s from ``ANGLE`` degrees off it) won the juker and lost the perimeter runner, and a lead that shrinks with the
target's own turn rate loses it too (``teacher_turn_lead.py``): near a wall a target's path is bent by the wall, so
leading it along its velocity now is not where a sideways runner goes back to. Here the side lead applies only to a
target at least ``WALL`` + 0.3 m from every wall, fading back to the full lead between ``WALL`` + 0.3 and ``WALL`` m
(linear). Everything the rule reads is in a pursuer's own observation (its position, the target's offset and
velocity), so a feed-forward student could learn it (``ClassicalPursuers.lead_side_wall``, ``train.teacher_side_wall``;
the output files were written by this script's first form, a subclass of ClassicalPursuers with the same rule, before
the option existed; its actions equal the option's to the bit on random states). The shipped recipe's teacher (push
``train.teacher_separation_gain``) flown through the config's avoidance layer, on validation episodes (evaluation
seeds 100 and 101 pooled, 200 episodes each per kind, the scripted fleeing evaders added); the classical team first,
as the bar. See results/README.md, twenty-ninth attempt.

    cd results/issue13 && ../../.venv/bin/python teacher_side_wall.py CONFIG SIDE@ANGLE@WALL [SIDE@ANGLE@WALL ...]
"""
import sys

from _layered import VALIDATION, LayeredClassical, print_suite_line, print_validation_bars
from training.config import ExperimentConfig


cfg = ExperimentConfig.from_toml(sys.argv[1])
print_validation_bars(cfg)
for arg in sys.argv[2:]:
    side, angle, wall = (float(x) for x in arg.split("@"))

    def make(side=side, angle=angle, wall=wall):
        t = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain)
        t.c.lead_side_time, t.c.lead_side_angle, t.c.lead_side_wall = side, angle, wall
        return t
    print_suite_line(cfg, f"teacher, lead 0.6 s along the line of sight, {side:g} s from {angle:g} deg off it, "
                     f"at least {wall:g} + 0.3 m from every wall", make, 200, **VALIDATION)
