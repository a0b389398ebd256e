"""What the learned team, its DAgger teacher (the classical team with push 1, through the avoidance layer) and the
classical team do differently in closed loop against one held-out suite kind: per-step means over 100 episodes
(evaluation seed 0's first round). min: the closest pursuer-evader pair [m] (the metric's per-step value); second:
the second-nearest pursuer's distance to its nearest evader; spread: each pursuer's distance to its nearest
teammate; near_mates: pursuer pairs closer than 0.5 m; speed / ev_speed: mean pursuer / evader speed [m/s];
ev_wall: the evaders' nearest wall distance [m]; close_share: the share of evaders within 0.3 m of a pursuer. Two more
rows: the teacher's pursuit (push 1) without the layer, and through a layer whose teammate barrier plans with 3 m/s^2.

    cd results/issue13 && ../../.venv/bin/python closed_loop.py SOURCE KIND     (SOURCE: runs/NAME or models/NAME)
"""
import dataclasses
import sys
import numpy as np
from _layered import LayeredClassical
from training.baselines import TeamPolicy, ClassicalPursuers
from training.env import PursuitEnv
from training.evaluate import eval_seed
from training.evader_suite import make_suite_evader
from training.learned_eval import load_source, team
from runtime.spec import Role

run, kind = sys.argv[1], sys.argv[2]
cfg, learned, _ = load_source(run)
spec = cfg.spec
P = np.asarray(spec.team.indices(Role.PURSUER)); nt = spec.team.n_team
hw = spec.arena.half_width
def stats(policy, label, eps=100):
    env = PursuitEnv(spec, cfg.rewards, n_envs=eps, seed=eval_seed(0, 0), track_metrics=True)
    obs = env.reset()
    acc = {k: [] for k in ("min", "second", "spread", "speed", "ev_wall", "ev_speed", "close_share", "near_mates")}
    for t in range(spec.timing.episode_steps):
        obs, _, done, info = env.step(policy.act(obs, env))
        s = env.state
        if done.all():
            break
        pp, ep = s.pos[:, P], s.pos[:, nt:]
        d = np.linalg.norm(pp[:, :, None] - ep[:, None], axis=-1)  # [B, P, E]
        acc["min"].append(d.reshape(len(d), -1).min(1))
        ds = np.sort(d.min(2), axis=1)
        acc["second"].append(ds[:, 1])
        dm = np.linalg.norm(pp[:, :, None] - pp[:, None], axis=-1) + np.eye(len(P)) * 99
        acc["spread"].append(dm.min(2).mean(1))
        acc["near_mates"].append((dm < 0.5).sum((1, 2)) / 2)
        acc["speed"].append(np.linalg.norm(s.vel[:, P], axis=-1).mean(1))
        acc["ev_speed"].append(np.linalg.norm(s.vel[:, nt:], axis=-1).mean(1))
        acc["ev_wall"].append((hw - np.abs(ep)).min(-1).min(-1))
        acc["close_share"].append((d.min(1) < 0.3).mean(1))
    m = {k: float(np.mean(v)) for k, v in acc.items()}
    print(f"{label:28s} " + "  ".join(f"{k} {v:.3f}" for k, v in m.items()), flush=True)

stats(team(learned, f"suite:{kind}", 0), "learned")
stats(TeamPolicy(LayeredClassical(spec, 1.0), make_suite_evader(kind, 0)), "teacher")
stats(TeamPolicy(ClassicalPursuers(), make_suite_evader(kind, 0)), "classical")
# the teacher's pursuit without the layer, and in a layer whose teammate barrier brakes at 3 m/s^2 (role_based's)
push1 = ClassicalPursuers()
push1.separation_gain = 1.0
stats(TeamPolicy(push1, make_suite_evader(kind, 0)), "push 1, no layer")
mates3 = dataclasses.replace(spec, avoidance=dataclasses.replace(spec.avoidance, teammate_braking=3.0))
stats(TeamPolicy(LayeredClassical(mates3, 1.0), make_suite_evader(kind, 0)), "teacher, teammate braking 3")
