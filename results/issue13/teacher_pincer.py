"""Would a teacher whose pursuers on one evader do different things be stronger than the classical team, whose
pursuers all fly at the same led point (the split's 2-3 per evader meet behind it, pushed apart only by the
separation term)? Variants of the DAgger teacher (push ``train.teacher_separation_gain``, through the config's
avoidance layer, as the students fly), each pursuer ranked by its distance among the pursuers on its evader
(rank 0 the nearest):

- ``stagger S``: rank r leads up to ``lead_time_max x (1 + S r)`` (the farther ones aim further ahead: interception
  rather than a chase);
- ``flank D``: ranks >= 1 aim ``D`` metres to alternate sides of the led point, across the evader's velocity (they
  close the escape routes beside it);
- ``cutoff D``: ranks >= 1 aim ``D`` metres ahead of the led point along the evader's velocity.

100 episodes per suite kind (evaluation seed 0: the same episodes as teacher_lead.py), min distance [m] / tracking
and team contacts per episode; the classical team itself first, as the bar.

    .venv/bin/python results/issue13/teacher_pincer.py [CONFIG] [EPISODES] [VARIANT ...]
        (configs/role_based.toml, 100, "base" "stagger 0.5" "stagger 1" "flank 0.3" "cutoff 0.4")
"""
import sys

import numpy as np

from _layered import LayeredClassical, print_suite_line
from training.baselines import ClassicalPursuers, _unit, assign_targets
from training.config import ExperimentConfig

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100
variants = sys.argv[3:] or ["base", "stagger 0.5", "stagger 1", "flank 0.3", "cutoff 0.4"]


class Pincer(ClassicalPursuers):
    mode, amount = "base", 0.0

    def _pursue(self, spec, pp, ep, ev, target=None):
        if target is None:
            target = assign_targets(pp, ep)
        b, p = target.shape
        bi = np.arange(b)[:, None]
        tp, tv = ep[bi, target], ev[bi, target]
        dist = np.linalg.norm(tp - pp, axis=-1)  # [B, P]
        # rank of each pursuer among those on the same target, by distance
        same = target[:, :, None] == target[:, None, :]
        closer = (dist[:, None, :] < dist[:, :, None]) | ((dist[:, None, :] == dist[:, :, None])
                                                          & (np.arange(p)[None, None, :] < np.arange(p)[None, :, None]))
        rank = (same & closer).sum(-1)  # [B, P]
        cap = np.full_like(dist, self.lead_time_max)
        if self.mode == "stagger":
            cap = self.lead_time_max * (1.0 + self.amount * rank)
        lead = np.minimum(dist / spec.pursuer.max_speed, cap)[..., None]
        goal = tp + tv * lead
        if self.mode in ("flank", "cutoff"):
            u = _unit(tv)
            if self.mode == "flank":
                side = np.where(rank % 2 == 1, 1.0, -1.0)[..., None]
                off = np.stack([-u[..., 1], u[..., 0]], -1) * side * self.amount
            else:
                off = u * self.amount
            goal = goal + np.where((rank >= 1)[..., None], off, 0.0)
        hw = spec.arena.half_width
        return _unit(np.clip(goal, -hw, hw) - pp)


print(f"{cfg.name}: avoidance {cfg.spec.avoidance}")
for v in variants:
    if v == "classical":
        print_suite_line(cfg, "classical team (no layer, push 3)", ClassicalPursuers, eps)
        continue
    mode, *amount = v.split()

    def make(mode=mode, amount=float(amount[0]) if amount else 0.0):
        t = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain)
        c = Pincer()
        c.separation_gain = t.c.separation_gain
        c.mode, c.amount = mode, amount
        t.c = c
        return t
    print_suite_line(cfg, f"teacher, {v}", make, eps)
