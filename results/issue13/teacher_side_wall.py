"""The side lead away from the walls: the twenty-eighth attempt's side lead (0.6 s along the line of sight, ``SIDE``
s from ``ANGLE`` degrees off it) won the juker and lost the perimeter runner, and a lead that shrinks with the
target's own turn rate loses it too (``teacher_turn_lead.py``): near a wall a target's path is bent by the wall, so
leading it along its velocity now is not where a sideways runner goes back to. Here the side lead applies only to a
target at least ``WALL`` + 0.3 m from every wall, fading back to the full lead between ``WALL`` + 0.3 and ``WALL`` m
(linear). Everything the rule reads is in a pursuer's own observation (its position, the target's offset and
velocity), so a feed-forward student could learn it. The shipped recipe's teacher (push
``train.teacher_separation_gain``) flown through the config's avoidance layer, on validation episodes (evaluation
seeds 100 and 101 pooled, 200 episodes each per kind, the scripted fleeing evaders added); the classical team first,
as the bar. See results/README.md, twenty-ninth attempt.

    cd results/issue13 && ../../.venv/bin/python teacher_side_wall.py CONFIG SIDE@ANGLE@WALL [SIDE@ANGLE@WALL ...]
"""
import sys

import numpy as np

from _layered import VALIDATION, LayeredClassical, print_suite_line
from training.baselines import ClassicalPursuers, _unit, assign_targets
from training.config import ExperimentConfig


class SideWall(ClassicalPursuers):
    """``ClassicalPursuers`` with the side lead faded out near the walls."""

    def __init__(self, side: float, angle: float, wall: float) -> None:
        self.side, self.angle, self.wall = side, angle, wall

    def _pursue(self, spec, pp, ep, ev, target=None):
        if target is None:
            target = assign_targets(pp, ep)
        bi = np.arange(pp.shape[0])[:, None]
        tp, tv = ep[bi, target], ev[bi, target]
        dist = np.linalg.norm(tp - pp, axis=-1, keepdims=True)
        full = self.lead_time_max
        speed = np.linalg.norm(tv, axis=-1, keepdims=True)
        along = (tv * (tp - pp)).sum(-1, keepdims=True) / np.maximum(dist * speed, 1e-9)
        along = np.where(speed > 1e-6, along, 1.0)
        c0 = np.cos(np.radians(self.angle))
        side = np.clip((1.0 - along) / (1.0 - c0), 0.0, 1.0)
        hw = spec.arena.half_width
        to_wall = (hw - np.abs(tp)).min(-1, keepdims=True)
        side = side * np.clip((to_wall - self.wall) / 0.3, 0.0, 1.0)
        lead = np.minimum(dist / spec.pursuer.max_speed, full - (full - self.side) * side)
        goal = np.clip(tp + tv * lead, -hw, hw)
        return _unit(goal - pp)


if __name__ == "__main__":
    cfg = ExperimentConfig.from_toml(sys.argv[1])
    print(f"{cfg.name}: avoidance {cfg.spec.avoidance}; evaluation seeds {VALIDATION['seeds']} pooled")
    print_suite_line(cfg, "classical team (lead 0.6 s, push 3, no layer)", ClassicalPursuers, 200, **VALIDATION)
    print_suite_line(cfg, "teacher (lead 0.6 s)", lambda: LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain),
                     200, **VALIDATION)
    for arg in sys.argv[2:]:
        side, angle, wall = (float(x) for x in arg.split("@"))

        def make(side=side, angle=angle, wall=wall):
            t = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain)
            push, t.c = t.c.separation_gain, SideWall(side, angle, wall)
            t.c.separation_gain = push
            return t
        print_suite_line(cfg, f"teacher, lead 0.6 s along the line of sight, {side:g} s from {angle:g} deg off it, "
                         f"at least {wall:g} + 0.3 m from every wall", make, 200, **VALIDATION)
