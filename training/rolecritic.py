"""``train.critic = "role"``: one centralized critic per role, with a head per agent of the role.

The paper's MADDPG keeps one critic per agent (12 for role_based), each evaluated on every sample in the
critic step, the target and the actor step. Agents of one role share their observations' meaning and their
reward's form, so here one critic per role present (pursuer, scout, evader; two with ``matd3``'s twins) reads
the compact global state (``training.maddpg.global_state``) and every agent's action and returns one value per
agent of that role: ``Q_r(S, A) -> [n_r]``, head j estimating agent j's own return. A step evaluates 3 critics
instead of 12.

Actor step (a role-level centralized policy gradient, as FACMAC does for a whole team): for each role r, the
joint action has every agent of r replaced by its actor's current output and every other agent's action from
the sample; agent i of r ascends its own head ``Q_r[i]``. Its actor therefore also receives the gradient of its
role-mates' heads through its action, so the agents of one role improve together (the pursuers' rewards are
team-aligned anyway), while the roles stay separate learners (the evaders never climb the pursuers' values).
TD3+BC's imitation term, the int8 penalty, parameter sharing, input scaling and ``matd3`` work as in
``MADDPG``.
"""
from __future__ import annotations

from typing import Any, Sequence

import torch
from torch import nn

from runtime.spec import SwarmSpec
from training.config import TrainConfig
from training import maddpg
from training.maddpg import MADDPG, _params_of, clip_grad_norm_per_agent, global_state, global_state_dim, soft_update
from training.networks import BatchedMLP, shared_linear


class RoleCritics(nn.Module):
    """``n_models`` (roles x twins) critics on ``[S, A]`` inputs, ``heads`` outputs each: ``[E, B, heads]``."""

    def __init__(self, n_models: int, in_dim: int, hidden: Sequence[int], heads: int,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.mlp = BatchedMLP(n_models, in_dim, hidden, heads, "none", generator)

    def forward(self, x: torch.Tensor, index: torch.Tensor | None = None) -> torch.Tensor:
        return self.mlp(x, index)

    def forward_split(self, state: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """Models ``0 .. E-1`` (twin 0 of each role) on the inputs ``[state, act[e]]``: ``state`` ``[B, S]``
        shared by the rows, ``act`` ``[E, B, A]`` per row -> ``[E, B, heads]``. The first layer is split into
        its state part (one GEMM for every row) and its action part, so that a gradient to the actions (the
        actor step) never goes through the state's columns. The weights are read detached: the actor step's
        gradient goes to the actions only, never into the critic's parameters."""
        e, s = act.shape[0], state.shape[1]
        ws, bs = self.mlp.tensors()
        weights, biases = [w.detach() for w in ws], [b.detach() for b in bs]
        w1 = weights[0][:e]
        h = torch.baddbmm(shared_linear(state, w1[:, :s], biases[0][:e]), act, w1[:, s:]).relu_()
        last = len(weights) - 1
        for k in range(1, last + 1):
            h = shared_linear(h, weights[k][:e], biases[k][:e])
            if k < last:
                h = h.relu_()
        return h


class RoleCriticMADDPG(MADDPG):
    """``MADDPG`` with ``RoleCritics`` (see the module docstring); everything else is inherited."""

    def __init__(self, spec: SwarmSpec, cfg: TrainConfig, device: str | torch.device | None = None) -> None:
        super().__init__(spec, cfg, device)
        dev = self.device
        roles = list(spec.roles)
        present = sorted(set(roles), key=roles.index)
        self.n_roles = len(present)
        role_of = [present.index(r) for r in roles]
        head_of = [roles[:i].count(r) for i, r in enumerate(roles)]
        heads = max(head_of) + 1
        n, t, nr = self.n_agents, self.twins, self.n_roles
        g = torch.Generator().manual_seed(cfg.seed + 9)
        in_dim = global_state_dim(spec) + 2 * n
        self.critics = RoleCritics(t * nr, in_dim, cfg.critic_hidden, heads, g).to(dev)
        self.critics_tgt = RoleCritics(t * nr, in_dim, cfg.critic_hidden, heads, g).to(dev)
        self.critics_tgt.load_state_dict(self.critics.state_dict())
        self.critics_tgt.requires_grad_(False)
        self.critic_opt = maddpg.adam(self.critics, cfg.critic_lr, self.critics_tgt)
        # agent i of twin k reads model k x R + role_of[i], head head_of[i]
        self._q_model = torch.tensor([k * nr + role_of[i] for k in range(t) for i in range(n)], device=dev)
        self._q_head = torch.tensor(head_of * t, device=dev)
        self._q_index = {k: (self._q_model[:k * n], self._q_head[:k * n]) for k in range(1, t + 1)}  # by twins
        member = torch.zeros(nr, n, dtype=torch.bool)
        member[role_of, torch.arange(n)] = True
        self._member = member.to(dev)  # [R, N]: agent i belongs to role r
        self._role_of = torch.tensor(role_of, device=dev)
        self._mine = (self._member & self._learns.view(1, -1)).view(nr, 1, n, 1)  # [R, 1, N, 1]: r's learners

    def critic_input(self, obs: torch.Tensor) -> torch.Tensor:
        return global_state(self.spec, obs)

    def _per_agent(self, q: torch.Tensor, twins: int) -> torch.Tensor:
        """Critic outputs ``[twins x R, B, heads]`` -> each agent's own value ``[twins x N, B]``."""
        ix = self._q_index[twins]
        return q[ix[0], :, ix[1]]

    @torch.no_grad()
    def td_target(self, batch: Sequence[torch.Tensor], next_state: torch.Tensor | None = None) -> torch.Tensor:
        rew, next_obs = batch[2], batch[3]
        k = next_obs.shape[0]
        next_act = self.target_next_actions(next_obs, batch[4] if len(batch) > 4 else None)
        if next_state is None:
            next_state = self.critic_input(next_obs)
        x = torch.cat([next_state, next_act.reshape(k, -1)], dim=1)
        q_next = self._per_agent(self.critics_tgt(x), self.twins)  # [T N, K]
        if self.twins > 1:
            q_next = q_next.view(self.twins, self.n_agents, k).amin(0)
        return rew.t() * self.cfg.reward_scale + self.cfg.gamma * q_next

    def update(self, batch: Sequence[torch.Tensor], imitation: bool = False,
               imitation_weight: float | None = None) -> dict[str, float]:
        obs, act = batch[0], batch[1]
        cfg = self.cfg
        k, n = obs.shape[0], self.n_agents
        state, next_state = self.critic_inputs(obs, batch[3])
        y = self.td_target(batch, next_state)
        q = self._per_agent(self.critics(torch.cat([state, act.reshape(k, -1)], dim=1)), self.twins)
        y_rows = y if self.twins == 1 else y.repeat(self.twins, 1)
        w_rows = self._weight if self.twins == 1 else self._weight.repeat(self.twins)
        critic_loss_n = (q - y_rows).pow(2).mean(1)
        self.critic_opt.zero_grad(set_to_none=True)
        (critic_loss_n * w_rows).sum().backward()
        critic_norm = clip_grad_norm_per_agent(_params_of(self.critics, self.critic_opt), cfg.grad_clip)
        self.critic_opt.step()
        self.updates += 1
        if cfg.algorithm != "matd3" or self.updates % cfg.policy_delay == 0:
            teach = batch[5] if len(batch) > 5 else None
            w_bc = cfg.imitation_weight if imitation_weight is None else imitation_weight
            self._last_actor = self._role_actor_step(obs, act, state, teach, imitation, w_bc)
            soft_update(self.actors_tgt, self.actors, cfg.tau)
            soft_update(self.critics_tgt, self.critics, cfg.tau)
        w = self._mean_w
        return {**self._last_actor, "critic_loss": float((critic_loss_n.detach()[:n] * w).sum()),
                "q_mean": float(q.detach()[:n].mean()), "critic_grad_norm": float(critic_norm.mean())}

    def _role_actor_step(self, obs: torch.Tensor, act: torch.Tensor, state: torch.Tensor,
                         teach: torch.Tensor | None, imitation: bool, w_bc: float) -> dict[str, float]:
        cfg = self.cfg
        k, n, nr = obs.shape[0], self.n_agents, self.n_roles
        pre = self.actors.forward_pre(obs.transpose(0, 1), self._actor_ix, self._in_scale, self._in_shift)
        mu = torch.tanh(pre)
        extra: dict[str, float] = {}
        bc_n = None
        if teach is not None and (imitation or w_bc > 0):
            bc_n = self._bc_loss(mu, teach, obs)
            extra["imitation_mse"] = float((bc_n.detach() * self.learn_mask).sum() / self.learn_mask.sum())
        if imitation:
            if bc_n is None:
                raise ValueError("an imitation update needs the batch's teacher actions (train.teacher)")
            loss_n = bc_n
        else:
            joint = torch.where(self._mine, mu.transpose(0, 1).unsqueeze(0), act.unsqueeze(0))  # [R, K, N, 2]
            q_pi = self._per_agent(self.critics.forward_split(state, joint.reshape(nr, k, 2 * n)), 1)  # twin 0
            if bc_n is not None:
                loss_n = -q_pi.mean(1) / q_pi.detach().abs().mean(1).clamp(min=1e-6) + w_bc * bc_n
            else:
                loss_n = -q_pi.mean(1)
        loss_n = loss_n + cfg.action_reg * pre.pow(2).mean((1, 2))
        if cfg.int8_robustness > 0:
            robust_n = self.int8_sensitivity(obs.transpose(0, 1))
            loss_n = loss_n + cfg.int8_robustness * robust_n
        self.actor_opt.zero_grad(set_to_none=True)
        (loss_n * self._weight).sum().backward()
        actor_norm = clip_grad_norm_per_agent(_params_of(self.actors, self.actor_opt), cfg.grad_clip)
        self.actor_opt.step()
        w = self._mean_w
        if cfg.int8_robustness > 0:
            extra["int8_sensitivity"] = float((robust_n.detach() * w).sum())
        return {**extra, "actor_loss": float((loss_n.detach() * w).sum()), "actor_grad_norm": float(actor_norm.mean())}


def make_learner(spec: SwarmSpec, cfg: TrainConfig, device: str | torch.device | None = None) -> MADDPG:
    """The learner ``train.critic`` asks for: ``RoleCriticMADDPG`` for "role", ``MADDPG`` otherwise."""
    cls: Any = RoleCriticMADDPG if cfg.critic == "role" else MADDPG
    return cls(spec, cfg, device)
