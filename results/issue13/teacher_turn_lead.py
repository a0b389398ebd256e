"""A teacher with memory of its target's turns: lead the target less only while it has been turning. The juker
(a zig-zag about its flee direction, a 60-140 degree turn every 0.4-1.6 s) turns often; the perimeter runner (a
90 degree turn at each corner, a lap of the walls taking seconds) and the predictive fleer seldom do. Each evader's
turn rate is the angle between its velocity now and one control period ago, over the period, averaged with time
constant ``TAU`` [s] (reset at every episode start); a pursuer leads its target ``lead_time_max`` (0.6 s) while that
rate is 0, down to ``SHORT`` s as it reaches ``RATE`` [rad/s] (linear; beyond it ``SHORT``). Everything else is the
shipped recipe's teacher (push ``train.teacher_separation_gain``) flown through the config's avoidance layer, on
validation episodes (evaluation seeds 100 and 101 pooled, 200 episodes each per kind, the scripted fleeing evaders
added); the classical team first, as the bar. A student could only learn this with the turn rate in its observation
(it is not there: a feed-forward student sees one control period), so this asks whether that memory would be worth
the change to the observation. See results/README.md, twenty-ninth attempt.

    cd results/issue13 && ../../.venv/bin/python teacher_turn_lead.py CONFIG SHORT@RATE@TAU [SHORT@RATE@TAU ...]
"""
import sys

import numpy as np

from _layered import VALIDATION, LayeredClassical, print_suite_line, print_validation_bars
from training.baselines import ClassicalPursuers, assign_targets
from training.config import ExperimentConfig


class TurnLead(ClassicalPursuers):
    """``ClassicalPursuers`` whose look-ahead on each evader shrinks with that evader's averaged turn rate."""

    def __init__(self, short: float, rate: float, tau: float) -> None:
        self.short, self.rate_ref, self.tau = short, rate, tau
        self._env = self._prev = self._rate = self._lead = None

    def act(self, obs, env):
        s, nt, dt = env.state, env.spec.team.n_team, env.spec.timing.control_period
        v = s.vel[:, nt:]
        if self._env is not env:
            self._env, self._prev, self._rate = env, v.copy(), np.zeros(v.shape[:2])
        sp, sq = np.linalg.norm(v, axis=-1), np.linalg.norm(self._prev, axis=-1)
        moving = (sp > 1e-3) & (sq > 1e-3)
        cos = (v * self._prev).sum(-1) / np.maximum(sp * sq, 1e-12)
        turn = np.where(moving, np.arccos(np.clip(cos, -1.0, 1.0)), 0.0) / dt
        a = min(dt / self.tau, 1.0)
        fresh = (s.step == 0)[:, None]
        self._rate = np.where(fresh, 0.0, (1 - a) * self._rate + a * turn)
        self._prev = v.copy()
        full = self.lead_time_max  # the class's (``_pursue`` sets its per-target lead on the instance only for a call)
        self._lead = full - (full - self.short) * np.clip(self._rate / self.rate_ref, 0.0, 1.0)  # [B, E]
        return super().act(obs, env)

    def _pursue(self, spec, pp, ep, ev, target=None):
        if target is None:
            target = assign_targets(pp, ep)
        bi = np.arange(pp.shape[0])[:, None]
        self.lead_time_max = self._lead[bi, target][..., None]  # [B, P, 1]
        try:
            return super()._pursue(spec, pp, ep, ev, target)
        finally:
            del self.lead_time_max


cfg = ExperimentConfig.from_toml(sys.argv[1])
print_validation_bars(cfg)
for arg in sys.argv[2:]:
    short, rate, tau = (float(x) for x in arg.split("@"))

    def make(short=short, rate=rate, tau=tau):
        t = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain)
        push, t.c = t.c.separation_gain, TurnLead(short, rate, tau)
        t.c.separation_gain = push
        return t
    print_suite_line(cfg, f"teacher, lead 0.6 s down to {short:g} s at a turn rate of {rate:g} rad/s "
                     f"(averaged over {tau:g} s)", make, 200, **VALIDATION)
