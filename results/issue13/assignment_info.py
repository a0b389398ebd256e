"""What the classical team's edge on the held-out suite owes to its centralized assignment. The classical team
(``ClassicalPursuers``) reads the whole state and splits the pursuers between the evaders by one Hungarian
assignment over every pursuer; a student sees its own state, both targets and its 4 nearest teammates (pursuers or
scouts, the observation does not say which). The same classical team with the assignment made from what one
pursuer could know, everything else (lead, separation, obstacles, walls, scouts) unchanged:

- ``central``: the shipped classical team (the bar);
- ``local_roles``: each pursuer runs the Hungarian assignment over itself and the pursuers among its 4 nearest
  teammates (it is told which of them are pursuers, which a student is not);
- ``local``: the same over itself and its 4 nearest teammates whatever their role (what the observation supports:
  ``ClassicalPursuers.assignment = "local"``, ``train.teacher_assignment = "local"``);
- ``nearest``: each pursuer pursues its nearest evader (no coordination).

100 episodes per kind, evaluation seed 0 (the screens' episodes); min distance [m] / tracking per kind and their
mean over the suite, and team contacts per episode.

    .venv/bin/python results/issue13/assignment_info.py [CONFIG] [EPISODES]   (configs/role_based.toml, 100)
"""
import sys

import numpy as np

from runtime.spec import Role
from training.baselines import ClassicalPursuers, TeamPolicy, assign_targets
from training.config import ExperimentConfig
from training.evader_suite import SUITE, make_suite_evader
from training.evaluate import evaluate, mean_of

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100
spec = cfg.spec
MATES = spec.sensing.n_teammates_observed


class LocalAssignment(ClassicalPursuers):
    def __init__(self, mode: str) -> None:
        self.mode = mode
        if mode == "local":
            self.assignment = "local"

    def act(self, obs, env):
        self._state = env.state
        return super().act(obs, env)

    def _pursue(self, spec, pp, ep, ev, target=None):
        if self.mode == "nearest":
            target = np.linalg.norm(pp[:, :, None] - ep[:, None], axis=-1).argmin(2)
        elif self.mode == "local_roles":  # the Hungarian method over itself and the pursuers among its 4 nearest
            s, nt = self._state, spec.team.n_team
            p_idx = np.asarray(spec.team.indices(Role.PURSUER))
            team = s.pos[:, :nt]
            dm = np.linalg.norm(team[:, p_idx, None] - team[:, None], axis=-1)  # [B, P, T]
            dm[:, np.arange(p_idx.size), p_idx] = np.inf
            near = np.argsort(dm, axis=2, kind="stable")[:, :, :MATES]  # each pursuer's 4 nearest teammates
            target = np.zeros(pp.shape[:2], dtype=np.int64)
            for bi in range(pp.shape[0]):
                for i in range(p_idx.size):
                    group = [pp[bi, i]] + [team[bi, t] for t in near[bi, i] if t in p_idx]
                    target[bi, i] = assign_targets(np.asarray(group)[None], ep[bi][None])[0, 0]
        return super()._pursue(spec, pp, ep, ev, target)


print(f"{cfg.name}: {eps} episodes per kind, evaluation seed 0; min distance [m] / tracking")
for mode in ("central", "local_roles", "local", "nearest"):
    per = {kind: evaluate(cfg, TeamPolicy(LocalAssignment(mode), make_suite_evader(kind, 0)), eps, seed=0,
                          progress=False) for kind in SUITE}
    m = mean_of(list(per.values()))
    print(f"{mode:12s} suite {m['mean_min_dist']:.3f}/{m['tracking_rate']:.3f} tc {m['team_contacts_per_episode']:.2f}   "
          + "  ".join(f"{k} {v['mean_min_dist']:.3f}/{v['tracking_rate']:.3f}" for k, v in per.items()), flush=True)
