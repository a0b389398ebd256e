"""Role-based MADDPG (the paper's section III on top of Lowe et al. 2017), with every agent batched.

One deterministic actor per agent (``actor_hidden`` ReLU layers, tanh output) and one centralized critic per
agent that sees every agent's observation and action. Roles differ only through their rewards (pursuer,
scout with the Voronoi term, evader), which the env computes; the critics exist for training only.

Speed: the ``N`` agents' networks are stacked into one module with per-agent weights ``[N, in, out]`` and
evaluated with one batched matmul per layer (``BatchedMLP``); losses are summed over agents, so one Adam
step over the stacked tensors is exactly N independent Adam steps (Adam is element-wise), and gradient
clipping is applied per agent (``clip_grad_norm_per_agent``).

Observations arrive zero-padded to ``D = spec.max_obs_dim``; an actor's weights on its padding columns see
only zero inputs, so they never matter and are dropped by ``BatchedMLP.to_actors`` when the per-agent
``training.networks.Actor`` modules are written (``training.checkpoint.save_actors``).

Actor update (per agent i, batched over i): ``Q_i(O, a_1 .. mu_i(o_i) .. a_N)`` with the other agents'
actions from the replay sample, as in the original MADDPG.
"""
from __future__ import annotations

import copy
import logging
import math
from typing import Any, NamedTuple, Sequence

import numpy as np
import torch
from torch import nn

from runtime.spec import INT8_QMAX, SwarmSpec
from training.config import TrainConfig
from training.networks import Actor

log = logging.getLogger(__name__)


class BatchedMLP(nn.Module):
    """``n_models`` independent MLPs evaluated together: ``[N, B, in] -> [N, B, out]``.

    Layer k has weight ``[N, in_k, out_k]`` and bias ``[N, 1, out_k]``; hidden layers use ReLU, the output
    layer ``out_act`` ("tanh" or "none"). ``forward`` also accepts an input shared by all models ``[B, in]``.
    """

    def __init__(self, n_models: int, in_dim: int, hidden: Sequence[int], out_dim: int, out_act: str = "none",
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        if out_act not in ("tanh", "none"):
            raise ValueError(f"out_act must be 'tanh' or 'none', got {out_act!r}")
        self.n_models = n_models
        self.widths = [in_dim, *hidden, out_dim]
        self.out_act = out_act
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(self.widths[:-1], self.widths[1:]):
            # nn.Linear's default initialisation, drawn per model
            bound = 1.0 / math.sqrt(fan_in)
            w = (torch.rand(n_models, fan_in, fan_out, generator=generator) * 2 - 1) * bound
            b = (torch.rand(n_models, 1, fan_out, generator=generator) * 2 - 1) * bound
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(b))

    def forward_pre(self, x: torch.Tensor) -> torch.Tensor:
        """Output before the output activation."""
        last = len(self.weights) - 1
        for k, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = torch.matmul(x, w) + b  # [B, in] broadcasts over the N models
            if k < last:
                x = torch.relu(x)
        return x

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.forward_pre(x)
        return torch.tanh(y) if self.out_act == "tanh" else y

    # -- the per-agent Actor contract -----------------------------------------------------------------
    def to_actors(self, in_dims: Sequence[int]) -> list[Actor]:
        """Per-model ``Actor(in_dims[i])`` with this model's weights; the first layer keeps only the first
        ``in_dims[i]`` input columns (the rest only ever saw zero padding)."""
        if self.out_act != "tanh":
            raise ValueError("only a tanh-output BatchedMLP is an actor")
        hidden = tuple(self.widths[1:-1])
        out = []
        for i, d in enumerate(in_dims):
            actor = Actor(int(d), self.widths[-1], hidden)
            sd = {}
            for k, (w, b) in enumerate(zip(self.weights, self.biases)):
                wi = w[i].detach().cpu()
                if k == 0:
                    wi = wi[:d]
                sd[f"net.{2 * k}.weight"] = wi.t().contiguous().clone()
                sd[f"net.{2 * k}.bias"] = b[i, 0].detach().cpu().clone()
            actor.load_state_dict(sd)
            out.append(actor)
        return out

    @classmethod
    def from_actors(cls, actors: Sequence[Actor], in_dim: int) -> "BatchedMLP":
        """Stack per-agent actors (equal hidden widths) into one module taking ``in_dim`` >= every obs_dim
        inputs; padding columns get zero weights."""
        hidden = actors[0].hidden
        if any(a.hidden != hidden or a.act_dim != actors[0].act_dim for a in actors):
            raise ValueError("actors must share hidden widths and act_dim to be batched")
        if any(a.obs_dim > in_dim for a in actors):
            raise ValueError(f"an actor takes more than in_dim={in_dim} inputs")
        m = cls(len(actors), in_dim, hidden, actors[0].act_dim, "tanh")
        with torch.no_grad():
            for i, a in enumerate(actors):
                linears = [mod for mod in a.net if isinstance(mod, nn.Linear)]
                for k, lin in enumerate(linears):
                    w = lin.weight.detach().t()
                    if k == 0:
                        m.weights[k][i].zero_()
                        m.weights[k][i, :a.obs_dim] = w
                    else:
                        m.weights[k][i] = w
                    m.biases[k][i, 0] = lin.bias.detach()
        return m


class BatchedCritic(nn.Module):
    """N centralized critics ``Q_i(O, A)``: O all observations ``[B, N*D]``, A all actions ``[B, N*2]``
    (or per-critic ``[N, B, ...]``); returns ``[N, B]``. The first layer is split into its observation and
    action parts so that the (large, shared) observation part is multiplied once per critic, not per
    action variant."""

    def __init__(self, n_agents: int, obs_in: int, act_in: int, hidden: Sequence[int],
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        h1 = hidden[0]
        bound = 1.0 / math.sqrt(obs_in + act_in)
        self.w_obs = nn.Parameter((torch.rand(n_agents, obs_in, h1, generator=generator) * 2 - 1) * bound)
        self.w_act = nn.Parameter((torch.rand(n_agents, act_in, h1, generator=generator) * 2 - 1) * bound)
        self.b1 = nn.Parameter((torch.rand(n_agents, 1, h1, generator=generator) * 2 - 1) * bound)
        self.rest = BatchedMLP(n_agents, h1, hidden[1:], 1, "none", generator)

    def obs_features(self, obs_flat: torch.Tensor) -> torch.Tensor:
        return torch.matmul(obs_flat, self.w_obs) + self.b1

    def forward(self, obs_flat: torch.Tensor, act_joint: torch.Tensor,
                obs_feat: torch.Tensor | None = None) -> torch.Tensor:
        if obs_feat is None:
            obs_feat = self.obs_features(obs_flat)
        h = torch.relu(obs_feat + torch.matmul(act_joint, self.w_act))
        return self.rest(h).squeeze(-1)


class Batch(NamedTuple):
    """A replay sample of ``K`` joint transitions. ``next_act`` holds the actions the agents took at
    ``next_obs`` where the trainer knows them (scripted agents' actions; zero where it passed none); the
    learner uses it for agents that do not learn, and the target actors for those that do."""

    obs: torch.Tensor  # [K, N, D]
    act: torch.Tensor  # [K, N, 2]
    rew: torch.Tensor  # [K, N]
    next_obs: torch.Tensor  # [K, N, D]
    next_act: torch.Tensor  # [K, N, 2]


class ReplayBuffer:
    """Preallocated ring buffer of joint transitions (obs ``[N, D]``, actions ``[N, 2]``, rewards ``[N]``,
    next obs ``[N, D]``, next actions ``[N, 2]``), float32 on ``device``."""

    FIELDS = ("obs", "act", "rew", "next_obs", "next_act")

    def __init__(self, capacity: int, n_agents: int, obs_dim: int, act_dim: int = 2,
                 device: str | torch.device = "cpu") -> None:
        self.capacity = capacity
        self.device = torch.device(device)
        kw = {"dtype": torch.float32, "device": self.device}
        self.obs = torch.zeros(capacity, n_agents, obs_dim, **kw)
        self.act = torch.zeros(capacity, n_agents, act_dim, **kw)
        self.rew = torch.zeros(capacity, n_agents, **kw)
        self.next_obs = torch.zeros(capacity, n_agents, obs_dim, **kw)
        self.next_act = torch.zeros(capacity, n_agents, act_dim, **kw)
        self.ptr = 0
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def add(self, obs: Any, act: Any, rew: Any, next_obs: Any, next_act: Any = None) -> None:
        """Append a batch of ``B`` transitions (numpy or torch), wrapping around when full. ``next_act``
        ``[B, N, 2]``: the actions taken at ``next_obs`` (needed for scripted agents, whose next action no
        target actor knows); None stores zeros (the static evaders' action)."""
        if next_act is None:
            next_act = torch.zeros_like(torch.as_tensor(act, dtype=torch.float32))
        values = (obs, act, rew, next_obs, next_act)
        tensors = [torch.as_tensor(x, dtype=torch.float32).to(self.device) for x in values]
        b = tensors[0].shape[0]
        if b > self.capacity:  # only the newest fit
            tensors = [t[-self.capacity:] for t in tensors]
            b = self.capacity
        idx = (self.ptr + torch.arange(b, device=self.device)) % self.capacity
        for name, t in zip(self.FIELDS, tensors):
            getattr(self, name)[idx] = t
        self.ptr = (self.ptr + b) % self.capacity
        self.size = min(self.size + b, self.capacity)

    def sample(self, batch: int, generator: torch.Generator) -> Batch:
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        idx = torch.randint(0, self.size, (batch,), generator=generator, device=self.device)
        return Batch(*(getattr(self, name)[idx] for name in self.FIELDS))

    def state_dict(self) -> dict[str, Any]:
        n = self.size
        # keep the order of insertion so that a reload with a different capacity keeps the newest
        order = (torch.arange(n, device=self.device) + (self.ptr - n)) % self.capacity
        return {name: getattr(self, name)[order].cpu() for name in self.FIELDS}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.ptr = 0
        self.size = 0
        if sd["obs"].shape[0]:
            if "next_act" not in sd:
                log.warning("replay buffer saved before next actions were stored: its %d transitions get zero "
                            "next actions (scripted agents' TD targets bootstrap on a zero action until they "
                            "are overwritten)", sd["obs"].shape[0])
            self.add(sd["obs"], sd["act"], sd["rew"], sd["next_obs"], sd.get("next_act"))


def clip_grad_norm_per_agent(params: Sequence[torch.Tensor], max_norm: float) -> torch.Tensor:
    """Scale the gradients of stacked parameters (leading dim = agent) so that each agent's global norm is at
    most ``max_norm``; returns the per-agent norms before clipping ``[N]``."""
    grads = [p.grad for p in params if p.grad is not None]
    sq = torch.stack([g.pow(2).reshape(g.shape[0], -1).sum(1) for g in grads]).sum(0)
    norms = sq.sqrt()
    if max_norm > 0:
        scale = (max_norm / (norms + 1e-6)).clamp(max=1.0)
        for g in grads:
            g.mul_(scale.view(-1, *([1] * (g.dim() - 1))))
    return norms


@torch.no_grad()
def soft_update(target: nn.Module, online: nn.Module, tau: float) -> None:
    """target <- tau x online + (1 - tau) x target."""
    for t, o in zip(target.parameters(), online.parameters()):
        t.lerp_(o, tau)


class MADDPG:
    """All agents' actors, critics, their targets and optimizers for one spec."""

    def __init__(self, spec: SwarmSpec, cfg: TrainConfig, device: str | torch.device | None = None) -> None:
        self.spec = spec
        self.cfg = cfg
        self.device = torch.device(device or cfg.device)
        n, d = spec.n_agents, spec.max_obs_dim
        self.n_agents, self.obs_dim = n, d
        self.obs_dims = [spec.obs_dim(r) for r in spec.roles]
        g = torch.Generator().manual_seed(cfg.seed)
        self.actors = BatchedMLP(n, d, cfg.actor_hidden, 2, "tanh", g)
        self.critics = BatchedCritic(n, n * d, n * 2, cfg.critic_hidden, g)
        self.actors_tgt = BatchedMLP(n, d, cfg.actor_hidden, 2, "tanh", g)
        self.critics_tgt = BatchedCritic(n, n * d, n * 2, cfg.critic_hidden, g)
        self.actors_tgt.load_state_dict(self.actors.state_dict())
        self.critics_tgt.load_state_dict(self.critics.state_dict())
        for m in (self.actors, self.critics, self.actors_tgt, self.critics_tgt):
            m.to(self.device)
        for m in (self.actors_tgt, self.critics_tgt):
            m.requires_grad_(False)
        self.actor_opt = torch.optim.Adam(self.actors.parameters(), lr=cfg.actor_lr)
        self.critic_opt = torch.optim.Adam(self.critics.parameters(), lr=cfg.critic_lr)
        learn = torch.ones(n, device=self.device)
        if cfg.evaders in ("static", "scripted"):  # scripted evaders' actions come from the trainer
            learn[spec.team.n_team:] = 0.0
        self.learn_mask = learn  # [N] 1 for agents whose actor and critic train
        self._learns = learn > 0
        self._eye = torch.eye(n, device=self.device).view(n, 1, n, 1)
        self.updates = 0
        # the int8-robustness penalty's observation ranges per agent ([N, 1, D], zero on the padding columns)
        lo = torch.zeros(n, 1, d)
        hi = torch.zeros(n, 1, d)
        for i, role in enumerate(spec.roles):
            r_lo, r_hi = spec.layout(role).bounds()
            lo[i, 0, :len(r_lo)] = torch.tensor(r_lo)
            hi[i, 0, :len(r_hi)] = torch.tensor(r_hi)
        self._obs_lo, self._obs_span = lo.to(self.device), (hi - lo).to(self.device)
        self.reg_gen = torch.Generator(device=self.device).manual_seed(cfg.seed + 7)

    # -------------------------------------------------------------------------------------- acting
    @torch.no_grad()
    def act(self, obs: np.ndarray | torch.Tensor, noise_std: float = 0.0,
            generator: torch.Generator | None = None) -> torch.Tensor:
        """Actions ``[B, N, 2]`` in [-1, 1] for observations ``[B, N, D]``, with Gaussian noise of std
        ``noise_std``. Static evaders always get zero."""
        o = torch.as_tensor(obs, dtype=torch.float32, device=self.device).transpose(0, 1)
        a = self.actors(o)  # [N, B, 2]
        if noise_std > 0:
            a = a + noise_std * torch.randn(a.shape, generator=generator, device=self.device)
        a = a.clamp(-1.0, 1.0) * self.learn_mask.view(-1, 1, 1)
        return a.transpose(0, 1)

    # ------------------------------------------------------------------------------------- learning
    @torch.no_grad()
    def td_target(self, batch: Sequence[torch.Tensor]) -> torch.Tensor:
        """``y_i = r_i x reward_scale + gamma x Q'_i(O', a'_1 .. a'_N)`` for every agent ``[N, K]``; a
        ``batch`` without next actions (4 tensors) bootstraps non-learning agents on a zero action."""
        rew, next_obs = batch[2], batch[3]
        k = next_obs.shape[0]
        next_act = self.target_next_actions(next_obs, batch[4] if len(batch) > 4 else None)
        q_next = self.critics_tgt(next_obs.reshape(k, -1), next_act.reshape(k, -1))
        return rew.t() * self.cfg.reward_scale + self.cfg.gamma * q_next

    def target_next_actions(self, next_obs: torch.Tensor, stored: torch.Tensor | None) -> torch.Tensor:
        """Next actions ``[K, N, 2]`` of the TD target: the target actors' for agents that learn, the stored
        ones (what the scripted agents did; zero when none were stored) for those that do not."""
        tgt = self.actors_tgt(next_obs.transpose(0, 1)).transpose(0, 1)
        if stored is None:
            stored = torch.zeros_like(tgt)
        return torch.where(self._learns.view(1, -1, 1), tgt, stored)

    def update(self, batch: tuple[torch.Tensor, ...]) -> dict[str, float]:
        """One critic step, one actor step and a soft target update for every agent at once."""
        obs, act, rew, next_obs = batch[:4]  # [K, N, D], [K, N, 2], [K, N], [K, N, D]
        cfg = self.cfg
        k, n = obs.shape[0], self.n_agents
        obs_flat = obs.reshape(k, -1)
        act_flat = act.reshape(k, -1)
        mask = self.learn_mask
        y = self.td_target(batch)
        obs_feat = self.critics.obs_features(obs_flat)
        q = self.critics(obs_flat, act_flat, obs_feat)
        critic_loss_n = (q - y).pow(2).mean(1)  # [N]
        self.critic_opt.zero_grad(set_to_none=True)
        (critic_loss_n * mask).sum().backward()
        critic_norm = clip_grad_norm_per_agent(list(self.critics.parameters()), cfg.grad_clip)
        self.critic_opt.step()

        # actor step: critic i sees agent i's action replaced by mu_i(o_i), the others from the sample
        pre = self.actors.forward_pre(obs.transpose(0, 1))  # [N, K, 2]
        mu = torch.tanh(pre)
        joint = act.unsqueeze(0) * (1 - self._eye) + mu.unsqueeze(2) * self._eye  # [N, K, N, 2]
        self.critics.requires_grad_(False)
        try:
            q_pi = self.critics(obs_flat, joint.reshape(n, k, -1), obs_feat.detach())
        finally:
            self.critics.requires_grad_(True)
        actor_loss_n = -q_pi.mean(1) + cfg.action_reg * pre.pow(2).mean((1, 2))
        if cfg.int8_robustness > 0:
            robust_n = self.int8_sensitivity(obs.transpose(0, 1))
            actor_loss_n = actor_loss_n + cfg.int8_robustness * robust_n
        self.actor_opt.zero_grad(set_to_none=True)
        (actor_loss_n * mask).sum().backward()
        actor_norm = clip_grad_norm_per_agent(list(self.actors.parameters()), cfg.grad_clip)
        self.actor_opt.step()

        soft_update(self.actors_tgt, self.actors, cfg.tau)
        soft_update(self.critics_tgt, self.critics, cfg.tau)
        self.updates += 1
        w = mask / mask.sum()
        extra = {"int8_sensitivity": float((robust_n.detach() * w).sum())} if cfg.int8_robustness > 0 else {}
        return {**extra, "critic_loss": float((critic_loss_n.detach() * w).sum()),
                "actor_loss": float((actor_loss_n.detach() * w).sum()),
                "q_mean": float(q.detach().mean()),
                "critic_grad_norm": float(critic_norm.mean()), "actor_grad_norm": float(actor_norm.mean())}

    def int8_sensitivity(self, obs: torch.Tensor, worst: float = 0.05) -> torch.Tensor:
        """Per agent [N]: the mean squared change of the actions on ``obs`` [N, K, D] and on K observations
        uniform within each agent's per-field ranges when every hidden layer's weights get uniform noise of
        one int8 step (``max|w| / INT8_QMAX`` per output neuron), plus the mean of the worst ``worst`` share
        of those changes (the C export is judged on its worst observation)."""
        n, k, _ = obs.shape
        rand = self._obs_lo + self._obs_span * torch.rand(n, k, obs.shape[2], generator=self.reg_gen,
                                                          device=self.device)
        x = torch.cat([obs, rand], dim=1)  # [N, 2K, D]
        noisy = x
        last = len(self.actors.weights) - 1
        for li, (w, b) in enumerate(zip(self.actors.weights, self.actors.biases)):
            if li < last:
                step = w.detach().abs().amax(dim=1, keepdim=True) / INT8_QMAX  # [N, 1, out]: per output neuron
                w = w + (torch.rand(w.shape, generator=self.reg_gen, device=self.device) - 0.5) * step
            noisy = torch.matmul(noisy, w) + b
            noisy = torch.relu(noisy) if li < last else torch.tanh(noisy)
        change = (noisy - self.actors(x)).pow(2).sum(-1)  # [N, 2K]
        top = max(1, int(round(worst * change.shape[1])))
        return change.mean(1) + change.topk(top, dim=1).values.mean(1)

    # --------------------------------------------------------------------------------- persistence
    def to_actors(self) -> list[Actor]:
        """Per-agent ``Actor`` modules with exactly ``spec.obs_dim(role)`` inputs (the export contract)."""
        return self.actors.to_actors(self.obs_dims)

    def state_dict(self) -> dict[str, Any]:
        return {"actors": self.actors.state_dict(), "critics": self.critics.state_dict(),
                "actors_tgt": self.actors_tgt.state_dict(), "critics_tgt": self.critics_tgt.state_dict(),
                "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
                "updates": self.updates, "reg_gen": self.reg_gen.get_state()}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.actors.load_state_dict(sd["actors"])
        self.critics.load_state_dict(sd["critics"])
        self.actors_tgt.load_state_dict(sd["actors_tgt"])
        self.critics_tgt.load_state_dict(sd["critics_tgt"])
        # torch keeps the given moment tensors (no copy when dtype and device match): copy them, so that a
        # state dict taken from a live learner is not shared with it
        self.actor_opt.load_state_dict(copy.deepcopy(sd["actor_opt"]))
        self.critic_opt.load_state_dict(copy.deepcopy(sd["critic_opt"]))
        self.updates = int(sd["updates"])
        if "reg_gen" in sd:  # absent in checkpoints written before the int8-robustness penalty
            self.reg_gen.set_state(sd["reg_gen"].cpu() if self.device.type == "cpu" else sd["reg_gen"])


# ------------------------------------------------------------------------------------------------
# trained actors as an evaluation policy (training.baselines.Policy)


class ActorsPolicy:
    """Every agent's trained actor, evaluated as one batched module: ``act(obs [B, N, D], env) -> [B, N, 2]``.

    Built from per-agent ``Actor`` modules (``training.checkpoint.load_actors``) or from an exported models
    folder (``OnnxActorsPolicy``). Deterministic: no exploration noise."""

    def __init__(self, actors: Sequence[Actor], obs_dim: int) -> None:
        self.net = BatchedMLP.from_actors(actors, obs_dim)
        self.net.requires_grad_(False)

    @torch.no_grad()
    def act(self, obs: np.ndarray, env: Any = None) -> np.ndarray:
        o = torch.as_tensor(obs, dtype=torch.float32).transpose(0, 1)
        return self.net(o).transpose(0, 1).numpy().astype(np.float64)


class OnnxActorsPolicy:
    """The ONNX actors of a models folder (``swarm-export onnx``), through ``runtime.policy``, batched per
    agent: what a drone runs, evaluated on the same episodes as the torch actors."""

    def __init__(self, folder: str, spec: SwarmSpec | None = None) -> None:
        from runtime.policy import load_models
        self.manifest, self.policies = load_models(folder, spec)
        self.spec = self.manifest.spec

    def act(self, obs: np.ndarray, env: Any = None) -> np.ndarray:
        out = np.zeros(obs.shape[:2] + (2,))
        for i, pol in enumerate(self.policies):
            out[:, i] = pol.act_batch(obs[:, i, :pol.obs_dim])
        return out
