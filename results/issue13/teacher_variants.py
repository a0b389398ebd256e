"""Teacher variants against the held-out suite (a probe for a stronger, non-tailored DAgger teacher): the classical
team's lead law changed, flown through the config's avoidance layer at push 1 (the shipped teacher's), beside the
classical team itself (the bar). Min distance [m] / tracking per kind (evaluation seed 0, as the evaluator).

    .venv/bin/python results/issue13/teacher_variants.py CONFIG EPISODES VARIANT ...

VARIANT: ``lead:L`` (lead_time_max L s on the instantaneous velocity), ``ema:TAU[:L]`` (lead on the target's velocity
smoothed with time constant TAU s; the teacher keeps that memory), ``flee:L`` (lead along the inverse-square flee
direction from the team, at the evader's top speed), ``scale:K:L`` (lead min(K distance / own speed, L)),
``mix:W:L`` (W of the flee lead, 1-W of the velocity lead), ``duo:L1:L2`` (among the pursuers sharing a target, the
nearest leads L1 s, the others L2 s), ``wall:LO:LW:D`` (lead LO s in the open, LW s at a wall, linear over the
target's first D m from the nearest wall).

Each VARIANT may end in ``@PUSH`` (the teacher's teammate push; 1, the shipped teacher's, by default) and
``@PUSH@MATES`` (the avoidance layer's ``teammate_braking`` [m/s^2] as well), e.g. ``lead:0.45@3@4.5``; ``base`` is
the classical lead law (``base@1@3``: the shipped teacher in a layer with teammate braking 3); ``MATES`` = ``none``
flies the variant without the layer (the classical team's way, contacts and all).
"""
import dataclasses
import sys

import numpy as np

from _layered import LayeredClassical, print_suite_line
from training.baselines import ClassicalPursuers, _unit, assign_targets
from training.config import ExperimentConfig


class VariantPursuers(ClassicalPursuers):
    def __init__(self, kind: str, args: list[float]):
        self.kind, self.args = kind, args
        self._ema = None
        self._env = None

    def act(self, obs, env):
        s = env.state
        nt = env.spec.team.n_team
        if self.kind == "ema":
            tau = self.args[0]
            a = min(1.0, env.spec.timing.control_period / tau)
            v = s.vel[:, nt:]
            if self._env is not env or self._ema is None or int(s.step.max()) == 0:
                self._ema, self._env = v.copy(), env
            else:
                self._ema = (1 - a) * self._ema + a * v
        self._team = s.pos[:, :nt]
        return super().act(obs, env)

    def _pursue(self, spec, pp, ep, ev, target=None):
        if target is None:
            target = assign_targets(pp, ep)
        bi = np.arange(pp.shape[0])[:, None]
        tp = ep[bi, target]
        dist = np.linalg.norm(tp - pp, axis=-1, keepdims=True)
        hw = spec.arena.half_width
        k = 1.0
        if self.kind == "lead":
            tv, lmax = ev[bi, target], self.args[0]
        elif self.kind == "duo":
            # the pursuer nearest its target (among those sharing it) leads by args[0] s, the others by args[1] s
            same = target[:, :, None] == target[:, None, :]
            closer = same & (dist[:, None, :, 0] < dist[:, :, None, 0])
            first = closer.sum(-1, keepdims=True) == 0
            tv = ev[bi, target]
            lmax = np.where(first, self.args[0], self.args[1])
        elif self.kind == "wall":
            # lead args[0] s in the open, args[1] s when the target is within args[2] m of a wall (linear between)
            gap = (hw - np.abs(tp)).min(-1, keepdims=True)
            f = np.clip(gap / self.args[2], 0.0, 1.0)
            tv, lmax = ev[bi, target], self.args[1] + (self.args[0] - self.args[1]) * f
        elif self.kind == "scale":
            tv, k, lmax = ev[bi, target], self.args[0], self.args[1]
        elif self.kind == "ema":
            tv, lmax = self._ema[bi, target], (self.args[1] if len(self.args) > 1 else self.lead_time_max)
        else:
            d = tp[:, :, None] - self._team[:, None]  # [B, P, T, 2]
            dd = np.sqrt((d * d).sum(-1))
            w = 1.0 / (dd + 0.2) ** 2
            flee = _unit(((w / np.maximum(dd, 1e-9))[..., None] * d).sum(2)) * spec.evader.max_speed
            if self.kind == "flee":
                tv, lmax = flee, self.args[0]
            else:
                wgt = self.args[0]
                tv, lmax = wgt * flee + (1 - wgt) * ev[bi, target], self.args[1]
        lead = np.minimum(k * dist / spec.pursuer.max_speed, lmax)
        goal = np.clip(tp + tv * lead, -hw, hw)
        return _unit(goal - pp)


class Unlayered:
    """A pursuer policy flown without the avoidance layer (``LayeredClassical``'s ``c`` alone)."""

    def __init__(self, c):
        self.c = c

    def act(self, obs, env):
        return self.c.act(obs, env)


if len(sys.argv) < 4:
    sys.exit(__doc__)
cfg = ExperimentConfig.from_toml(sys.argv[1])
eps = int(sys.argv[2])
print_suite_line(cfg, "classical team (lead 0.6 s, push 3, no layer)", ClassicalPursuers, eps)
print_suite_line(cfg, "teacher (push 1, lead 0.6 s)", lambda: LayeredClassical(cfg.spec, 1.0), eps)
for arg in sys.argv[3:]:
    law, *opts = arg.split("@")
    push = float(opts[0]) if opts else 1.0
    mates = opts[1] if len(opts) > 1 else None
    kind, *rest = law.split(":")
    run_cfg = cfg
    if mates not in (None, "none"):
        run_cfg = dataclasses.replace(cfg, spec=dataclasses.replace(
            cfg.spec, avoidance=dataclasses.replace(cfg.spec.avoidance, teammate_braking=float(mates))))

    def make(kind=kind, rest=[float(x) for x in rest], push=push, spec=run_cfg.spec, layered=mates != "none"):
        c = ClassicalPursuers() if kind == "base" else VariantPursuers(kind, rest)
        c.separation_gain = push
        if not layered:
            return Unlayered(c)
        t = LayeredClassical(spec, push)
        t.c = c
        return t
    print_suite_line(run_cfg, f"teacher {arg}", make, eps)
