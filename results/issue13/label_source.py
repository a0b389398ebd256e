"""What the classical team's labels near a target are made of, by distance to the nearest evader.

The same episodes as ``clone_error.py`` (the classical team against the held-out wanderer and hider, 50 episodes
each, suite parameters of seed 5, world seed 123). For every pursuer and step: whether the Hungarian assignment
(which reads every pursuer's position) sends it to an evader other than its nearest; the cosine between the label
(``full_speed_labels``) and its pursuit wish alone (the led direction to the assigned evader, before teammate
separation, obstacle and wall terms); the cosine between the label and the straight direction to the nearest
evader. A label that is not a function of what the pursuer observes cannot be cloned, however fine the inputs.

    .venv/bin/python results/issue13/label_source.py
"""
import numpy as np
from training.baselines import ClassicalPursuers, TeamPolicy, assign_targets
from training.config import ExperimentConfig
from training.env import PursuitEnv
from training.evader_suite import make_suite_evader
from training.train import full_speed_labels
from runtime.spec import Role

cfg = ExperimentConfig.from_toml("configs/role_based.toml")
spec = cfg.spec
P = np.asarray(spec.team.indices(Role.PURSUER))
nt = spec.team.n_team
bins = [0, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 10]
acc = {k: {"n": 0, "other": 0, "cos_wish": [], "cos_near": []} for k in range(len(bins) - 1)}
cp = ClassicalPursuers()


def cos(a, b):
    return (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1) + 1e-9)


for kind in ("wanderer", "hider"):
    env = PursuitEnv(spec, cfg.rewards, n_envs=50, seed=123)
    obs = env.reset()
    teacher = TeamPolicy(cp, make_suite_evader(kind, 5))
    for step in range(spec.timing.episode_steps):
        a = teacher.act(obs, env)
        lab = full_speed_labels(a[:, :nt].copy())[:, P]
        s = env.state
        pp, ep = s.pos[:, P], s.pos[:, nt:]
        dist = np.linalg.norm(pp[:, :, None] - ep[:, None], axis=-1)  # [B, P, E]
        nearest, d = dist.argmin(-1), dist.min(-1)
        assigned = assign_targets(pp, ep)
        wish = cp._pursue(spec, pp, ep, s.vel[:, nt:])
        bi = np.arange(pp.shape[0])[:, None]
        straight = ep[bi, nearest] - pp
        cw, cn = cos(lab, wish), cos(lab, straight)
        for k in range(len(bins) - 1):
            m = (d >= bins[k]) & (d < bins[k + 1])
            acc[k]["n"] += int(m.sum())
            acc[k]["other"] += int((assigned != nearest)[m].sum())
            acc[k]["cos_wish"] += list(cw[m])
            acc[k]["cos_near"] += list(cn[m])
        obs, _, _, _ = env.step(a)
print("classical labels by distance to the nearest evader [m]: share assigned elsewhere, cos(label, pursuit wish), "
      "cos(label, straight to nearest)")
for k in range(len(bins) - 1):
    v = acc[k]
    if v["n"]:
        print(f"d in [{bins[k]:.2f},{bins[k+1]:.2f}) n={v['n']:6d} assigned elsewhere={v['other'] / v['n']:.3f} "
              f"cos(label, wish)={np.mean(v['cos_wish']):.3f} cos(label, straight)={np.mean(v['cos_near']):.3f}")
