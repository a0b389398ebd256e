"""A teacher that leads on the evaders' low-passed velocity: against the juker (a zig-zag about the flee direction) the
mean heading is where the target goes, so would leading on an exponential moving average of each evader's velocity
(time constant ``tau``) instead of its velocity now make a stronger DAgger teacher? The shipped recipe's teacher (push
``train.teacher_separation_gain``, lead 0.6 s) flown through the config's avoidance layer, on validation episodes
(evaluation seeds 100 and 101 pooled, 200 episodes each per kind, the scripted fleeing evaders added); the classical
team first, as the bar. Dropped: see results/README.md, twenty-eighth attempt.

    cd results/issue13 && ../../.venv/bin/python teacher_ema.py [CONFIG] [EPISODES] [TAU ...]   (configs/role_based.toml,
                                                                                                200, 0.2 0.4 0.8)
"""
import sys

import numpy as np

from _layered import VALIDATION, LayeredClassical, print_suite_line, print_validation_bars
from training.baselines import ClassicalPursuers
from training.config import ExperimentConfig

class EmaClassical(ClassicalPursuers):
    """``ClassicalPursuers`` leading on each evader's velocity averaged with time constant ``tau`` [s] (reset at
    every episode start); everything else the classical team's."""

    def __init__(self, tau: float) -> None:
        self.tau, self._env, self._ema = tau, None, None

    def act(self, obs, env):
        s, nt = env.state, env.spec.team.n_team
        v = s.vel[:, nt:]
        if self._env is not env:
            self._env, self._ema = env, v.copy()
        a = env.spec.timing.control_period / self.tau
        self._ema = np.where((s.step == 0)[:, None, None], v, (1 - a) * self._ema + a * v)
        real = s.vel
        s.vel = real.copy()
        s.vel[:, nt:] = self._ema
        try:
            return super().act(obs, env)
        finally:
            s.vel = real


cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "../../configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 200
taus = [float(x) for x in sys.argv[3:]] or [0.2, 0.4, 0.8]
print_validation_bars(cfg, "teacher (velocity now)", eps)
for tau in taus:
    def make(tau=tau):
        t = LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain)
        push, t.c = t.c.separation_gain, EmaClassical(tau)
        t.c.separation_gain = push
        return t
    print_suite_line(cfg, f"teacher, velocity averaged over {tau:g} s", make, eps, **VALIDATION)
