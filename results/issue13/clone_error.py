"""How well a run's pursuer actors clone the classical team, by distance to the nearest evader.

The classical team flies 50 episodes against the held-out wanderer and 50 against the hider (evaluation-suite
parameters of seed 5, world seed 123); at every step each pursuer's actor is asked for its action on the same
observation and compared with the teacher's label (``training.train.full_speed_labels``, what DAgger regresses
on): mean squared error and mean cosine between the two, binned by the pursuer's distance to the nearest evader.

    .venv/bin/python results/issue13/clone_error.py runs/RUN      (RUN: a run folder with actors.pt)
        [--teacher own] [--kinds KIND,...] [--actors FILE]

``--teacher own``: the labels of the run's own DAgger teacher (its ``train.teacher_separation_gain``,
``teacher_assignment`` and ``teacher_obstacle_softness``) instead of the classical team's; ``--kinds``: the suite
kinds flown (wanderer,hider); ``--actors``: another actors file of the run (e.g. ``snapshots/actors_005000.pt``,
the clone before ES).
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
opts = dict(zip(sys.argv[2::2], sys.argv[3::2]))
unknown = set(opts) - {"--teacher", "--kinds", "--actors"}
if unknown or opts.get("--teacher", "own") != "own":
    sys.exit(f"clone_error.py: unknown option(s) {sorted(unknown) or opts['--teacher']!r}: see the docstring")
own = opts.get("--teacher") == "own"
kinds = opts.get("--kinds", "wanderer,hider").split(",")
actors_file = opts.get("--actors", "actors.pt")
cfg = ExperimentConfig.from_toml(f"{run}/config.toml")
print(f"{run} ({actors_file}): pursuers against the {'run teacher' if own else 'classical team'}'s labels on "
      f"{','.join(kinds)}, by distance to the nearest evader [m]")
spec, agents, _ = load_actors(f"{run}/{actors_file}")
actors = [a for _, _, a in agents]
P = spec.team.indices(Role.PURSUER)
nt = spec.team.n_team
bins = [0, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 10]
errs = {i: [] for i in range(len(bins) - 1)}
cos = {i: [] for i in range(len(bins) - 1)}
for kind in kinds:
    env = PursuitEnv(cfg.spec, cfg.rewards, n_envs=50, seed=123)
    obs = env.reset()
    pursuers = ClassicalPursuers()
    if own:  # as training.train.Trainer builds its teacher
        pursuers.separation_gain = cfg.train.teacher_separation_gain
        pursuers.assignment = cfg.train.teacher_assignment
        pursuers.obstacle_side_softness = cfg.train.teacher_obstacle_softness
    teacher = TeamPolicy(pursuers, make_suite_evader(kind, 5))
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
