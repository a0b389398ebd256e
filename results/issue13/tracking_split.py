"""Where the students' tracking is lost against the held-out evaders: per (step, evader), the nearest pursuer's
distance in bands (touching, 0.15-0.3, 0.3-0.5 m, beyond the 0.5 m sensing range = not tracked), how many pursuers
have that evader as their nearest, per step how many of the evaders are tracked (0, 1, both), and the share of
untracked (step, evader) pairs with an obstacle across the segment from the nearest pursuer to the evader, and
the share of pursuer-steps stalled at an obstacle (within 0.2 m of its surface at under a third of full speed). The shipped
models against the classical team on the same episodes (evaluation seed 0, ``EPISODES`` per kind).

    .venv/bin/python results/issue13/tracking_split.py [MODELS | RUN] [EPISODES] [KINDS]
    (models/role_based, 100, hider,perimeter,juker,wanderer,predictive)
"""
import sys

import numpy as np

from runtime.spec import Role
from training.baselines import ClassicalPursuers, TeamPolicy
from training.env import PursuitEnv
from training.evaluate import eval_seed
from training.evader_suite import make_suite_evader
from training.learned_eval import load_source

models = sys.argv[1] if len(sys.argv) > 1 else "models/role_based"
episodes = int(sys.argv[2]) if len(sys.argv) > 2 else 100
kinds = (sys.argv[3] if len(sys.argv) > 3 else "hider,perimeter,juker,wanderer,predictive").split(",")
cfg, learned, _ = load_source(models)
spec = cfg.spec
pursuers = np.array([i for i, r in enumerate(spec.roles) if r == Role.PURSUER])
nt = spec.team.n_team
rng = spec.sensing.sensing_range
BANDS = (0.15, 0.3, rng)


def rollout(policy) -> dict[str, np.ndarray]:
    near, per_evader, tracked_n, blocked, stalled, captures = [], [], [], [], [], 0
    n_envs = 50
    for r in range((episodes + n_envs - 1) // n_envs):
        b = min(n_envs, episodes - r * n_envs)
        env = PursuitEnv(spec, cfg.rewards, n_envs=b, seed=eval_seed(0, r), track_metrics=True)
        obs = env.reset()
        for _ in range(spec.timing.episode_steps):
            obs, _, done, info = env.step(policy.act(obs, env))
            pos = env.state.pos
            d = np.linalg.norm(pos[:, pursuers, None] - pos[:, None, nt:], axis=-1)  # [B, P, E]
            nd = d.min(1)  # [B, E]
            near.append(nd.ravel())
            tracked_n.append((nd <= rng).sum(1))
            per_evader.append(np.stack([(d.argmin(2) == e).sum(1) for e in range(d.shape[2])], 1).ravel())
            a = pos[np.arange(b)[:, None], pursuers[d.argmin(1)]]  # [B, E, 2]: each evader's nearest pursuer
            ev = pos[:, nt:]
            c = env.state.obstacle_pos[:, None]  # [B, 1, K, 2]
            seg = (ev - a)[:, :, None]
            t = np.clip(((c - a[:, :, None]) * seg).sum(-1) / np.maximum((seg * seg).sum(-1), 1e-12), 0, 1)
            gap = np.linalg.norm(a[:, :, None] + t[..., None] * seg - c, axis=-1)  # [B, E, K]
            hit = (gap < env.state.obstacle_radius[:, None]).any(-1)
            blocked.append(hit[nd > rng])
            pp = pos[:, pursuers]
            surf = (np.linalg.norm(pp[:, :, None] - env.state.obstacle_pos[:, None], axis=-1)
                    - env.state.obstacle_radius[:, None] - spec.pursuer.radius).min(-1)
            slow = np.linalg.norm(env.state.vel[:, pursuers], axis=-1) < spec.pursuer.max_speed / 3
            stalled.append(((surf < 0.2) & slow).ravel())
        captures += sum(rec.captures for rec in info["episodes"])
    return {"near": np.concatenate(near), "per": np.concatenate(per_evader), "n": np.concatenate(tracked_n),
            "blocked": np.concatenate(blocked), "stalled": np.concatenate(stalled), "captures": captures / episodes}


def line(name: str, x: dict[str, np.ndarray]) -> str:
    nd, per, n = x["near"], x["per"], x["n"]
    edges = (0.0, *BANDS, np.inf)
    bands = [((nd > lo) & (nd <= hi)).mean() if lo > 0 else (nd <= hi).mean() for lo, hi in zip(edges, edges[1:])]
    nb = [(n == k).mean() for k in range(3)]
    pe = [(per == k).mean() for k in range(len(pursuers) + 1)]
    return (f"  {name:9s} tracking {(nd <= rng).mean():.3f} | nearest pursuer <=0.15 {bands[0]:.3f} 0.15-0.3 "
            f"{bands[1]:.3f} 0.3-0.5 {bands[2]:.3f} >0.5 {bands[3]:.3f} | evaders tracked 0/1/2: "
            + "/".join(f"{v:.3f}" for v in nb) + " | pursuers nearest to an evader 0.." + str(len(pursuers)) + ": "
            + " ".join(f"{v:.2f}" for v in pe) + f" | untracked behind an obstacle {x['blocked'].mean():.3f} | stalled at an obstacle {x['stalled'].mean():.3f}"
            f" | captures/ep {x['captures']:.1f}")


print(f"{models}: {cfg.name}, {len(pursuers)} pursuers, {spec.team.n_evaders} evaders, sensing {rng} m, "
      f"{episodes} episodes per kind, evaluation seed 0")
for kind in kinds:
    print(kind)
    print(line("students", rollout(TeamPolicy(learned, make_suite_evader(kind, 0)))), flush=True)
    print(line("classical", rollout(TeamPolicy(ClassicalPursuers(), make_suite_evader(kind, 0)))), flush=True)
