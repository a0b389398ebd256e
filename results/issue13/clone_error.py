"""How well a run's pursuer actors clone the classical team, by distance to the nearest evader.

The classical team flies 50 episodes against the held-out wanderer and 50 against the hider (evaluation-suite
parameters of seed 5, world seed 123); at every step each pursuer's actor is asked for its action on the same
observation and compared with the teacher's label (``training.train.full_speed_labels``, what DAgger regresses
on): mean squared error and mean cosine between the two, binned by the pursuer's distance to the nearest evader.

    .venv/bin/python results/issue13/clone_error.py runs/RUN      (RUN: a run folder with actors.pt)
"""
import sys
import numpy as np, torch
from training.baselines import ClassicalPursuers, TeamPolicy
from training.config import ExperimentConfig
from training.env import PursuitEnv
from training.evader_suite import make_suite_evader
from training.checkpoint import load_actors
from training.train import full_speed_labels
from runtime.spec import Role

run = sys.argv[1]
print(f"{run}: pursuers against the classical team's labels, by distance to the nearest evader [m]")
cfg = ExperimentConfig.from_toml(f"{run}/config.toml")
spec, agents, _ = load_actors(f"{run}/actors.pt")
actors = [a for _, _, a in agents]
P = spec.team.indices(Role.PURSUER)
nt = spec.team.n_team
bins = [0, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 10]
errs = {i: [] for i in range(len(bins) - 1)}
cos = {i: [] for i in range(len(bins) - 1)}
for kind in ("wanderer", "hider"):
    env = PursuitEnv(cfg.spec, cfg.rewards, n_envs=50, seed=123)
    obs = env.reset()
    teacher = TeamPolicy(ClassicalPursuers(), make_suite_evader(kind, 5))
    for step in range(cfg.spec.timing.episode_steps):
        a = teacher.act(obs, env)
        lab = full_speed_labels(a[:, :nt].copy())
        with torch.no_grad():
            stu = np.stack([actors[i](torch.as_tensor(obs[:, i, :actors[i].obs_dim], dtype=torch.float32)).numpy()
                            for i in P], 1)
        s = env.state
        d = np.linalg.norm(s.pos[:, P, None] - s.pos[:, None, nt:], axis=-1).min(-1)  # [B, P]
        t = lab[:, P]
        e = ((stu - t) ** 2).sum(-1)
        c = (stu * t).sum(-1) / (np.linalg.norm(stu, axis=-1) * np.linalg.norm(t, axis=-1) + 1e-9)
        for k in range(len(bins) - 1):
            m = (d >= bins[k]) & (d < bins[k + 1])
            errs[k] += list(e[m]); cos[k] += list(c[m])
        obs, _, done, _ = env.step(a)
for k in range(len(bins) - 1):
    if errs[k]:
        print(f"d in [{bins[k]:.2f},{bins[k+1]:.2f}) n={len(errs[k]):6d} mse={np.mean(errs[k]):.3f} cos={np.mean(cos[k]):.3f}")
