"""A teacher whose look-ahead shortens when its target runs off the line of sight: a target running sideways to its
pursuer (as the juker does, zig-zagging about its flee direction) is likely to turn back, so lead it less. Each
pursuer leads ``lead_time_max`` (0.6 s) while the target's velocity points along the bearing from the pursuer to it,
and down to ``SIDE`` s as the angle between them grows to ``ANGLE`` degrees (linear in the cosine; beyond it, and
toward the pursuer, ``SIDE``). Everything the teacher reads is in a pursuer's own observation (the target's offset and
velocity), so a feed-forward student could learn it. The shipped recipe's teacher (push
``train.teacher_separation_gain``) flown through the config's avoidance layer, on validation episodes (evaluation
seeds 100 and 101 pooled, 200 episodes each per kind, the scripted fleeing evaders added). Not trained: see
results/README.md, twenty-eighth attempt.

    cd results/issue13 && ../../.venv/bin/python teacher_side_lead.py CONFIG SIDE@ANGLE [SIDE@ANGLE ...]
"""
import sys

import numpy as np

from _layered import LayeredClassical, print_suite_line
from training.baselines import ClassicalPursuers, _unit, assign_targets
from training.config import ExperimentConfig


class SideLead(ClassicalPursuers):
    """``ClassicalPursuers`` whose lead shortens to ``side_lead`` [s] as the target runs off the line of sight."""

    def __init__(self, side_lead: float, full_angle_deg: float) -> None:
        self.side_lead, self.c0 = side_lead, float(np.cos(np.radians(full_angle_deg)))

    def _pursue(self, spec, pp, ep, ev, target=None):
        if target is None:
            target = assign_targets(pp, ep)
        bi = np.arange(pp.shape[0])[:, None]
        tp, tv = ep[bi, target], ev[bi, target]
        rel = tp - pp
        dist = np.linalg.norm(rel, axis=-1, keepdims=True)
        speed = np.linalg.norm(tv, axis=-1, keepdims=True)
        cos = np.where(speed > 1e-6, (tv * rel).sum(-1, keepdims=True) / np.maximum(dist * speed, 1e-9), 1.0)
        off = np.clip((1 - cos) / (1 - self.c0), 0, 1)
        lead = np.minimum(dist / spec.pursuer.max_speed, self.lead_time_max - (self.lead_time_max - self.side_lead) * off)
        hw = spec.arena.half_width
        return _unit(np.clip(tp + tv * lead, -hw, hw) - pp)


cfg = ExperimentConfig.from_toml(sys.argv[1])
extra = {"seeds": (100, 101), "scripted": True, "digits": 4}
print(f"{cfg.name}: avoidance {cfg.spec.avoidance}; evaluation seeds {extra['seeds']} pooled")
print_suite_line(cfg, "classical team (lead 0.6 s, push 3, no layer)", ClassicalPursuers, 200, **extra)
print_suite_line(cfg, "teacher (lead 0.6 s)", lambda: LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain),
                 200, **extra)
for arg in sys.argv[2:]:
    side, angle = (float(x) for x in arg.split("@"))

    def make(side=side, angle=angle):
        t = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain)
        push, t.c = t.c.separation_gain, SideLead(side, angle)
        t.c.separation_gain = push
        return t
    print_suite_line(cfg, f"teacher, lead 0.6 s along the line of sight, {side:g} s from {angle:g} deg off it", make,
                     200, **extra)
