"""How far the DAgger clone still is from the teacher when the imitation phase ends, and how much more cloning
steps bring it closer: the run's learner and replay buffer as its last checkpoint left them (the end of DAgger),
the newest 16,384 transitions held out, then STEPS more cloning steps (batch ``imitation_batch``, learning rate
``actor_lr``, or annealed by a cosine to 1e-5 with ``cos``) on the rest. Prints the mean squared distance to the
teacher's actions per role on the held-out transitions (unweighted, then with the run's row weights) four times.

    .venv/bin/python results/issue13/polish_probe.py runs/rb_v12_ow4_s0 16000 [const|cos]

The fifteenth attempt's outputs: polish_probe_rb.txt, polish_probe_mt.txt (results/README.md)."""
import math
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from training.config import ExperimentConfig  # noqa: E402
from training.train import Trainer  # noqa: E402

run, n = Path(sys.argv[1]), int(sys.argv[2])
mode = sys.argv[3] if len(sys.argv) > 3 else "const"
cfg = ExperimentConfig.from_toml(run / "config.toml")
scratch = tempfile.TemporaryDirectory(prefix="polish_probe_")  # the Trainer's run folder, removed at exit
tr = Trainer(cfg, scratch.name, init_from=run)
ag, buf = tr.agent, tr.buffer
held = 16384
train_n = buf.size - held  # the buffer was loaded oldest first: the newest transitions are the last rows
o_ev, t_ev = buf.obs[train_n:buf.size], buf.teach[train_n:buf.size]


def clone_error() -> tuple[dict[str, float], dict[str, float]]:
    with torch.no_grad():
        mu = torch.tanh(ag.actors.forward_pre(o_ev.transpose(0, 1), ag._actor_ix, ag._in_scale, ag._in_shift))
        t = t_ev.transpose(0, 1)
        has = torch.isfinite(t).all(-1)
        sq = torch.where(has, (mu - torch.nan_to_num(t)).pow(2).sum(-1), torch.zeros(()))
        plain = sq.sum(1) / has.sum(1).clamp(min=1)
        weighted = ag._bc_loss(mu, t_ev, o_ev)  # the loss the clone is trained on (the run's row weights)
    return ({r: round(float(plain[ix].mean()), 5) for r, ix in tr.role_idx.items()},
            {r: round(float(weighted[ix].mean()), 5) for r, ix in tr.role_idx.items()})


print(f"{run} ({mode}): held-out clone error, unweighted / weighted: at the end of DAgger {clone_error()}",
      flush=True)
lr0, t0 = cfg.train.actor_lr, time.time()
for i in range(n):
    lr = 1e-5 + (lr0 - 1e-5) * 0.5 * (1 + math.cos(math.pi * i / n)) if mode == "cos" else lr0
    for group in ag.actor_opt.param_groups:
        group["lr"] = lr
    idx = torch.randint(0, train_n, (cfg.train.imitation_batch,), generator=tr.sample_gen)
    ag.clone_step(buf.obs[idx], buf.teach[idx])
    if (i + 1) % max(1, n // 4) == 0:
        print(f"after {i + 1} steps ({time.time() - t0:.0f} s, lr {lr:.1e}): {clone_error()}", flush=True)
