"""Role-based MADDPG (the paper's section III on top of Lowe et al. 2017), with every agent batched.

One deterministic actor per agent (``actor_hidden`` ReLU layers, tanh output) and one centralized critic per
agent that sees every agent's observation and action. Roles differ only through their rewards (pursuer,
scout with the Voronoi term, evader), which the env computes; the critics exist for training only.

Speed: the ``N`` agents' networks are stacked into one module with per-agent weights ``[N, in, out]`` and
evaluated with one batched matmul per layer (``BatchedMLP``); losses are summed over agents, so one Adam
step over the stacked tensors is exactly N independent Adam steps (Adam is element-wise), and gradient
clipping is applied per agent (``clip_grad_norm_per_agent``). The actors' and the critics' tensors live in one
buffer each (``FlatAdam``: Adam, zeroing the gradients and the soft target update are one call), and the
actors' activations in buffers reused from update to update (``training.networks._PooledMLP``); both compute
the same values bit for bit as the straightforward forms (``tests/test_learner_speed.py``).

Observations arrive zero-padded to ``D = spec.max_obs_dim``; an actor's weights on its padding columns see
only zero inputs, so they never matter and are dropped by ``BatchedMLP.to_actors`` when the per-agent
``training.networks.Actor`` modules are written (``training.checkpoint.save_actors``).

Actor update (per agent i, batched over i): ``Q_i(O, a_1 .. mu_i(o_i) .. a_N)`` with the other agents'
actions from the replay sample, as in the original MADDPG.
"""
from __future__ import annotations

import contextlib
import copy
import logging
import weakref
from typing import Any, Iterator, NamedTuple, Sequence

import numpy as np
import torch
import torch.optim.optimizer as _optim
from torch import nn

from runtime.avoidance import avoid_agents
from runtime.spec import INT8_QMAX, SpecError, SwarmSpec
from training.config import TrainConfig
from training.networks import Actor, BatchedCritic, BatchedMLP

log = logging.getLogger(__name__)


class Batch(NamedTuple):
    """A replay sample of ``K`` joint transitions. ``next_act`` holds the actions the agents took at
    ``next_obs`` where the trainer knows them (scripted agents' actions), NaN elsewhere; the learner uses the
    known ones in its TD target and its target actors for the others (``MADDPG.target_next_actions``)."""

    obs: torch.Tensor  # [K, N, D]
    act: torch.Tensor  # [K, N, 2]
    rew: torch.Tensor  # [K, N]
    next_obs: torch.Tensor  # [K, N, D]
    next_act: torch.Tensor  # [K, N, 2]
    teach: torch.Tensor | None = None  # [K, N, 2]: the teacher's action at obs (train.teacher), NaN: none


class _Ring:
    """A preallocated ring of tensors, one per name in ``FIELDS`` (first dimension: the slot), on ``device``."""

    FIELDS: tuple[str, ...] = ()
    capacity: int
    device: torch.device
    ptr: int = 0
    size: int = 0
    what = "ring"

    def __len__(self) -> int:
        return self.size

    def _write(self, values: Sequence[Any]) -> None:
        """Append a batch of ``B`` rows, one value per field (numpy or torch), wrapping around when full."""
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

    def sample_fields(self, batch: int, generator: torch.Generator, fields: Sequence[str]) -> list[torch.Tensor]:
        """``batch`` random rows' ``fields`` only (a cloning step needs the observations and the teacher's
        actions, not the rest: the gather from a large buffer is most of a big sample's cost)."""
        if self.size == 0:
            raise ValueError(f"cannot sample from an empty {self.what}")
        idx = torch.randint(0, self.size, (batch,), generator=generator, device=self.device)
        return [getattr(self, name)[idx] for name in fields]

    def state_dict(self) -> dict[str, Any]:
        n = self.size
        # keep the order of insertion so that a reload with a different capacity keeps the newest
        order = (torch.arange(n, device=self.device) + (self.ptr - n)) % self.capacity
        return {name: getattr(self, name)[order].cpu() for name in self.FIELDS}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """The rows of ``state_dict``, oldest first (a smaller capacity keeps the newest)."""
        self.ptr = 0
        self.size = 0
        if sd[self.FIELDS[0]].shape[0]:
            self._write([sd[name] for name in self.FIELDS])


class ReplayBuffer(_Ring):
    """Preallocated ring buffer of joint transitions (obs ``[N, D]``, actions ``[N, 2]``, rewards ``[N]``,
    next obs ``[N, D]``, next actions ``[N, 2]``, the teacher's actions at obs ``[N, 2]``, NaN without one),
    float32 on ``device``."""

    FIELDS = ("obs", "act", "rew", "next_obs", "next_act", "teach")
    what = "replay buffer"

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
        self.teach = torch.full((capacity, n_agents, act_dim), float("nan"), **kw)
        self.ptr = 0
        self.size = 0

    def add(self, obs: Any, act: Any, rew: Any, next_obs: Any, next_act: Any = None, teach: Any = None) -> None:
        """Append a batch of ``B`` transitions (numpy or torch), wrapping around when full. ``next_act``
        ``[B, N, 2]``: the actions taken at ``next_obs`` (needed for scripted agents, whose next action no
        target actor knows); NaN entries (and None: all) mean unknown, so the learner takes its target
        actors' next action there (zero for agents that do not learn). ``teach`` ``[B, N, 2]``: the teacher's
        actions at ``obs`` (``train.teacher``); None: no teacher (NaN)."""
        if next_act is None:  # unknown: the target actors decide (zero for agents that do not learn)
            next_act = torch.full_like(torch.as_tensor(act, dtype=torch.float32), float("nan"))
        if teach is None:
            teach = torch.full_like(torch.as_tensor(act, dtype=torch.float32), float("nan"))
        self._write((obs, act, rew, next_obs, next_act, teach))

    def sample(self, batch: int, generator: torch.Generator) -> Batch:
        return Batch(*self.sample_fields(batch, generator, self.FIELDS))

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.ptr = 0
        self.size = 0
        if sd["obs"].shape[0]:
            if "next_act" not in sd:
                log.warning("replay buffer saved without next actions: its %d transitions bootstrap on the "
                            "target actors (zero for agents that do not learn) until they are overwritten",
                            sd["obs"].shape[0])
            self.add(sd["obs"], sd["act"], sd["rew"], sd["next_obs"], sd.get("next_act"), sd.get("teach"))


class CloneBuffer(_Ring):
    """Preallocated ring buffer of behaviour-cloning rows only: observations ``[N, D]`` and the teacher's actions
    ``[N, 2]`` at them, float32 on ``device`` (``train.imitation_augment``'s rows, which no env step follows)."""

    FIELDS = ("obs", "teach")
    what = "clone buffer"

    def __init__(self, capacity: int, n_agents: int, obs_dim: int, act_dim: int = 2,
                 device: str | torch.device = "cpu") -> None:
        self.capacity = capacity
        self.device = torch.device(device)
        self.obs = torch.zeros(capacity, n_agents, obs_dim, dtype=torch.float32, device=self.device)
        self.teach = torch.zeros(capacity, n_agents, act_dim, dtype=torch.float32, device=self.device)
        self.ptr = 0
        self.size = 0

    def add(self, obs: Any, teach: Any) -> None:
        """Append ``B`` rows (numpy or torch), wrapping around when full."""
        self._write((obs, teach))


def clip_grad_norm_per_agent(params: Sequence[torch.Tensor], max_norm: float) -> torch.Tensor:
    """Scale the gradients of stacked parameters (leading dim = agent) so that each agent's global norm is at
    most ``max_norm``; returns the per-agent norms before clipping ``[N]``."""
    grads = [p.grad for p in params if p.grad is not None]
    sq = torch.stack([torch.linalg.vector_norm(g.reshape(g.shape[0], -1), dim=1) for g in grads]).pow(2).sum(0)
    norms = sq.sqrt()
    if max_norm > 0:
        scale = (max_norm / (norms + 1e-6)).clamp(max=1.0)
        torch._foreach_mul_(grads, [scale.view(-1, *([1] * (g.dim() - 1))) for g in grads])
    return norms


def _params_of(module: nn.Module, opt: Any) -> list[torch.Tensor]:
    """``list(module.parameters())``, from the optimizer's ``FlatParams`` when it has them (the same list, made
    once: walking the module's tree is a noticeable share of a small update)."""
    flat = getattr(opt, "flat", None)
    return flat.params if flat is not None else list(module.parameters())


class FlatParams:
    """Every parameter of ``module`` moved into one contiguous buffer ``data`` (each parameter a view of it, in
    ``module.parameters()`` order), and with ``grads`` every gradient into ``grad`` likewise (each ``p.grad`` a
    view that backward passes accumulate into), so that Adam, zeroing the gradients and the soft target update
    are one call on one tensor each instead of one per tensor. The values are the same bit for bit: those
    calls are element-wise. The module must not be moved (``.to``) afterwards."""

    def __init__(self, module: nn.Module, grads: bool = True) -> None:
        self.params = list(module.parameters())
        first = self.params[0]
        self.data = torch.empty(sum(p.numel() for p in self.params), dtype=first.dtype, device=first.device)
        self.grad = torch.zeros_like(self.data) if grads else None
        self.views: list[torch.Tensor] = []
        self.grad_views: list[torch.Tensor] = []
        off = 0
        with torch.no_grad():
            for p in self.params:
                n = p.numel()
                self.data[off:off + n].copy_(p.reshape(-1))
                p.data = self.data[off:off + n].view_as(p)
                self.views.append(p.data)
                if self.grad is not None:
                    p.grad = self.grad[off:off + n].view_as(p)
                    self.grad_views.append(p.grad)
                off += n
        _FLAT[module] = self

    def sync_grads(self) -> None:
        """Make sure the buffer ``grad`` holds every parameter's gradient: a gradient that something replaced
        (``p.grad = ...``, or set to None) is copied back in and the view restored."""
        for p, v, g in zip(self.params, self.views, self.grad_views):
            if p.data.data_ptr() != v.data_ptr():
                raise RuntimeError("a flattened parameter was replaced (module moved or .data assigned); build "
                                   "the optimizer after the module is in place")
            if p.grad is not g:
                if p.grad is None:
                    g.zero_()
                else:
                    g.copy_(p.grad)
                p.grad = g


_FLAT: "weakref.WeakKeyDictionary[nn.Module, FlatParams]" = weakref.WeakKeyDictionary()
"""Modules whose parameters ``FlatParams`` moved into one buffer (``soft_update`` reads it)."""


class FlatAdam:
    """Fused Adam on a module's ``FlatParams``: one tensor per step. The same steps as ``torch.optim.Adam(
    module.parameters(), fused=True)``, bit for bit (Adam is element-wise), and the same ``state_dict`` layout
    (per parameter, as that optimizer's), so checkpoints written by either load into both."""

    def __init__(self, module: nn.Module, lr: float) -> None:
        self.flat = FlatParams(module)
        self.param = nn.Parameter(self.flat.data)  # shares the buffer
        self.param.grad = self.flat.grad
        self.opt = torch.optim.Adam([self.param], lr=lr, fused=True)

    @property
    def param_groups(self) -> list[dict[str, Any]]:
        return self.opt.param_groups

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Zero the gradient buffer (``set_to_none`` is accepted and ignored: the buffer stays)."""
        self.flat.sync_grads()
        self.flat.grad.zero_()

    def step(self) -> None:
        self.flat.sync_grads()
        self.param.grad = self.flat.grad
        st = self.opt.state.get(self.param)
        if not st:  # the first step: the optimizer makes its state (moments, step count) as it likes it
            self.opt.step()
            return
        # then what torch.optim.Adam(fused=True).step() calls (torch/optim/adam.py, _fused_adam), without its
        # Python around it (hooks, profiler records, grouping by device): the same kernel on the same tensors
        g = self.opt.param_groups[0]
        if g["amsgrad"] or g["maximize"] or g["weight_decay"] or g.get("decoupled_weight_decay") or \
                isinstance(g["lr"], torch.Tensor) or self.opt._optimizer_step_pre_hooks or \
                self.opt._optimizer_step_post_hooks or _optim._global_optimizer_pre_hooks or \
                _optim._global_optimizer_post_hooks:
            self.opt.step()
            return
        step = st["step"]
        step.add_(1)
        beta1, beta2 = g["betas"]
        torch._fused_adam_([self.param], [self.flat.grad], [st["exp_avg"]], [st["exp_avg_sq"]], [], [step],
                           amsgrad=False, lr=g["lr"], beta1=beta1, beta2=beta2, weight_decay=0.0, eps=g["eps"],
                           maximize=False, grad_scale=None, found_inf=None)

    def state_dict(self) -> dict[str, Any]:
        """``torch.optim.Adam``'s layout over the module's parameters (the moments split per parameter)."""
        sd = self.opt.state_dict()
        group = {**sd["param_groups"][0], "params": list(range(len(self.flat.params)))}
        state: dict[int, dict[str, torch.Tensor]] = {}
        if 0 in sd["state"]:
            st, off = sd["state"][0], 0
            for i, p in enumerate(self.flat.params):
                n = p.numel()
                state[i] = {key: (v.clone() if v.dim() == 0 else v[off:off + n].view_as(p).clone())
                            for key, v in st.items()}
                off += n
        return {"state": state, "param_groups": [group]}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """A ``state_dict`` of this class or of ``torch.optim.Adam`` over the same module's parameters."""
        groups = sd["param_groups"]
        n = len(self.flat.params)
        if len(groups) != 1 or len(groups[0]["params"]) != n:
            raise ValueError(f"optimizer state for {[len(g['params']) for g in groups]} parameters, this module "
                             f"has {n}: use the run's own config.toml")
        state = {}
        ids = groups[0]["params"]
        if any(i in sd["state"] for i in ids):
            per = [sd["state"][i] for i in ids]
            state[0] = {key: (per[0][key] if per[0][key].dim() == 0
                              else torch.cat([st[key].reshape(-1) for st in per]))
                        for key in per[0]}
        self.opt.load_state_dict({"state": state, "param_groups": [{**groups[0], "params": [0]}]})


@torch.no_grad()
def soft_update(target: nn.Module, online: nn.Module, tau: float) -> None:
    """target <- tau x online + (1 - tau) x target: one call on the flat buffers when both modules have them
    (``FlatParams``), else one fused call over every tensor."""
    flat_t, flat_o = _FLAT.get(target), _FLAT.get(online)
    if flat_t is not None and flat_o is not None:
        flat_t.data.lerp_(flat_o.data, tau)
        return
    torch._foreach_lerp_(list(target.parameters()), [p.detach() for p in online.parameters()], tau)


def adam(online: nn.Module, lr: float, target: nn.Module | None = None) -> FlatAdam:
    """The learner's optimizer for ``online``: fused Adam on its parameters moved into one buffer
    (``FlatAdam``), and ``target``'s parameters into one buffer too (``soft_update``: one call)."""
    if target is not None:
        FlatParams(target, grads=False)
    return FlatAdam(online, lr)


def global_state_dim(spec: SwarmSpec) -> int:
    """Size of ``global_state``: 4 per agent (position, velocity) + 3 per observed obstacle."""
    return 4 * spec.n_agents + 3 * spec.layout(spec.roles[0])["obstacles"].rows


_COLUMNS: dict[tuple[int, str], tuple[SwarmSpec, torch.Tensor, Any, int]] = {}


def _global_state_columns(spec: SwarmSpec, device: torch.device) -> tuple[torch.Tensor, Any, int]:
    """``global_state``'s columns of every agent's position then every agent's velocity in a flattened joint
    observation ``[4 N]`` (agent i's column c at ``i x max_obs_dim + c``), the obstacle block's layout and
    ``spec.max_obs_dim``, built once per spec and device (the spec's layouts and a new index tensor cost more
    than the gather itself on a learner's batch)."""
    key = (id(spec), str(device))
    hit = _COLUMNS.get(key)
    if hit is None or hit[0] is not spec:  # the spec is kept in the entry, so its id is not reused meanwhile
        d = spec.max_obs_dim
        pos, vel = [], []
        for i, role in enumerate(spec.roles):
            lay = spec.layout(role)
            sp, sv = lay["self_pos"].start, lay["self_vel"].start
            pos += [i * d + sp, i * d + sp + 1]
            vel += [i * d + sv, i * d + sv + 1]
        hit = _COLUMNS[key] = (spec, torch.tensor(pos + vel, device=device),
                               spec.layout(spec.roles[0])["obstacles"], d)
    return hit[1], hit[2], hit[3]


def global_state(spec: SwarmSpec, obs: torch.Tensor) -> torch.Tensor:
    """The global state ``[K, 4N + 3M]`` of joint observations ``[K, N, D]``: every agent's position, then
    every agent's velocity [m, m/s; world frame], then every obstacle's centre and radius [m], obstacles
    ordered by x so that their order stays fixed through an episode.

    Read from the observations, which carry each agent's own position and velocity exactly and every
    obstacle (``sensing.n_obstacles_observed >= arena.n_obstacles``, checked by ``MADDPG``) under either
    observability: so it needs nothing beyond what the replay buffer stores, and the final observation of
    an episode (``info["final_obs"]``) gives the final state."""
    k, n, d = obs.shape
    cols, ob, width = _global_state_columns(spec, obs.device)
    if d != width:
        raise ValueError(f"global_state: observations of {d} columns, the spec's are {width} wide")
    pv = obs.reshape(k, n * d).index_select(1, cols)  # [K, 4N]: positions, then velocities
    o = obs[:, 0, ob.slice].reshape(k, ob.rows, 3)
    centre = o[..., :2] + pv[:, None, :2]  # agent 0 sees them relative to itself
    obst = torch.cat([centre, o[..., 2:]], dim=-1)
    order = centre[..., 0].argsort(dim=1)
    obst = torch.gather(obst, 1, order.unsqueeze(-1).expand(k, ob.rows, 3))
    return torch.cat([pv, obst.reshape(k, -1)], dim=1)


OPTIONS = ("algorithm", "critic", "share_params", "obs_scaling", "obs_offset_gain")
"""The ``TrainConfig`` fields that shape the learner's tensors (a state dict loads only into the same)."""


class MADDPG:
    """All agents' actors, critics, their targets and optimizers for one spec.

    Options (``TrainConfig``): ``share_params`` (one actor and critic per role), ``critic = "global"`` (the
    critics read ``global_state`` instead of every observation), ``algorithm = "matd3"`` (twin critics,
    target policy smoothing, delayed actor and target updates), ``obs_scaling`` (actor inputs mapped to
    [-1, 1] from the spec's ranges). With every option off the learner is the paper's MADDPG, computed
    exactly as before the options existed."""

    def __init__(self, spec: SwarmSpec, cfg: TrainConfig, device: str | torch.device | None = None) -> None:
        self.spec = spec
        self.cfg = cfg
        self.device = dev = torch.device(device or cfg.device)
        n, d = spec.n_agents, spec.max_obs_dim
        self.n_agents, self.obs_dim = n, d
        self.obs_dims = [spec.obs_dim(r) for r in spec.roles]
        roles = list(spec.roles)
        if cfg.share_params:  # model m serves every agent of the m-th role present; slot: agent within role
            present = sorted(set(roles), key=roles.index)
            self.model_of = [present.index(r) for r in roles]
            slot = [roles[:i].count(r) for i, r in enumerate(roles)]
        else:
            self.model_of, slot = list(range(n)), [0] * n
        m = self.n_models = max(self.model_of) + 1
        self.twins = 2 if cfg.algorithm == "matd3" else 1
        if cfg.critic in ("global", "role"):
            if spec.sensing.n_obstacles_observed < spec.arena.n_obstacles:
                raise SpecError(f"train.critic = {cfg.critic!r} reads the obstacles from the observations: it needs "
                                f"sensing.n_obstacles_observed >= arena.n_obstacles ({spec.arena.n_obstacles}), "
                                f"got {spec.sensing.n_obstacles_observed}")
            critic_in = global_state_dim(spec)
        else:
            critic_in = n * d
        # row r of a critic call is (twin r // N, agent r % N): model twin x M + model_of[agent]
        rows = [t * m + self.model_of[i] for t in range(self.twins) for i in range(n)]
        self._actor_ix = _index(self.model_of, m, dev)
        self._critic_ix = _index(rows, self.twins * m, dev)
        self._actor_critic_ix = _index(rows[:n], self.twins * m, dev)  # the actor step asks twin 0
        self._slot = torch.tensor(slot * self.twins, device=dev) if cfg.share_params else None
        n_slots = max(slot) + 1 if cfg.share_params else 0
        g = torch.Generator().manual_seed(cfg.seed)
        self.actors = BatchedMLP(m, d, cfg.actor_hidden, 2, "tanh", g)
        self.critics = BatchedCritic(self.twins * m, critic_in, n * 2, cfg.critic_hidden, g, n_slots)
        self.actors_tgt = BatchedMLP(m, d, cfg.actor_hidden, 2, "tanh", g)
        self.critics_tgt = BatchedCritic(self.twins * m, critic_in, n * 2, cfg.critic_hidden, g, n_slots)
        self.actors_tgt.load_state_dict(self.actors.state_dict())
        self.critics_tgt.load_state_dict(self.critics.state_dict())
        for mod in (self.actors, self.critics, self.actors_tgt, self.critics_tgt):
            mod.to(dev)
        for mod in (self.actors_tgt, self.critics_tgt):
            mod.requires_grad_(False)
        self.actor_opt = adam(self.actors, cfg.actor_lr, self.actors_tgt)
        self.critic_opt = adam(self.critics, cfg.critic_lr, self.critics_tgt)
        learn = torch.ones(n, device=dev)
        if cfg.evaders in ("static", "scripted"):  # scripted evaders' actions come from the trainer
            learn[spec.team.n_team:] = 0.0
        self.learn_mask = learn  # [N] 1 for agents whose actor and critic train
        self._mean_w = learn / learn.sum()  # [N] weights of the mean over the learning agents
        self._learns = learn > 0
        self._all_learn = bool(self._learns.all())
        # per-agent loss weights: a shared model averages over the agents it serves (sum without sharing)
        share = torch.tensor([1.0 / self.model_of.count(self.model_of[i]) for i in range(n)], device=dev)
        self._weight = learn if not cfg.share_params else learn * share
        self._eye = torch.eye(n, device=dev).view(n, 1, n, 1)
        self.updates = 0
        # the observation ranges per agent ([N, 1, D], zero on the padding columns): the int8-robustness
        # penalty's random observations and the obs_scaling map
        lo = torch.zeros(n, 1, d)
        hi = torch.zeros(n, 1, d)
        gain = torch.ones(n, 1, d)  # train.obs_offset_gain on the offset columns
        for i, role in enumerate(spec.roles):
            layout = spec.layout(role)
            r_lo, r_hi = layout.bounds()
            lo[i, 0, :len(r_lo)] = torch.tensor(r_lo)
            hi[i, 0, :len(r_hi)] = torch.tensor(r_hi)
            offset = [c in ("dx", "dy") for f in layout.fields for _ in range(f.rows) for c in f.columns]
            gain[i, 0, :len(offset)][torch.tensor(offset)] = cfg.obs_offset_gain
        self._obs_lo, self._obs_span = lo.to(dev), (hi - lo).to(dev)
        self._near = _near_columns(spec, dev) if cfg.imitation_near_weight != 1.0 else None
        self._obstacle = _obstacle_columns(spec, dev) if cfg.imitation_obstacle_weight != 1.0 else None
        self._walls = _wall_columns(spec, dev) if cfg.imitation_obstacle_walls else None
        self._weighted_rows = any(x is not None for x in (self._near, self._obstacle, self._walls))
        self._in_scale = self._in_shift = None
        if cfg.obs_scaling:  # x -> gain (2 (x - lo) / span - 1); padding columns (span 0) stay 0
            span = hi - lo
            scale = torch.where(span > 0, 2.0 / span.clamp(min=1e-12), torch.zeros(()))
            self._in_scale = (scale * gain).to(dev)
            self._in_shift = (torch.where(span > 0, -lo * scale - 1.0, torch.zeros(())) * gain).to(dev)
        self.reg_gen = torch.Generator(device=dev).manual_seed(cfg.seed + 7)
        self.target_gen = torch.Generator(device=dev).manual_seed(cfg.seed + 8)
        self._last_actor: dict[str, float] = {}

    def options(self) -> dict[str, Any]:
        return {name: getattr(self.cfg, name) for name in OPTIONS}

    # -------------------------------------------------------------------------------------- acting
    def actor_input(self, obs: torch.Tensor) -> torch.Tensor:
        """What the actors see of observations ``[N, B, D]`` (scaled with ``obs_scaling``)."""
        return obs if self._in_scale is None else obs * self._in_scale + self._in_shift

    @torch.no_grad()
    def act(self, obs: np.ndarray | torch.Tensor, noise_std: float = 0.0,
            generator: torch.Generator | None = None) -> torch.Tensor:
        """Actions ``[B, N, 2]`` in [-1, 1] for observations ``[B, N, D]``, with Gaussian noise of std
        ``noise_std``. Static evaders always get zero."""
        o = torch.as_tensor(obs, dtype=torch.float32, device=self.device).transpose(0, 1)
        a = self.actors(o, self._actor_ix, self._in_scale, self._in_shift)  # [N, B, 2]
        if noise_std > 0:
            a = a + noise_std * torch.randn(a.shape, generator=generator, device=self.device)
        a = a.clamp(-1.0, 1.0) * self.learn_mask.view(-1, 1, 1)
        return a.transpose(0, 1)

    # ------------------------------------------------------------------------------------- learning
    def critic_input(self, obs: torch.Tensor) -> torch.Tensor:
        """The critics' state input ``[K, S]`` of joint observations ``[K, N, D]``."""
        if self.cfg.critic == "global":
            return global_state(self.spec, obs)
        return obs.reshape(obs.shape[0], -1)

    def critic_inputs(self, obs: torch.Tensor, next_obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``critic_input`` of ``obs`` and of ``next_obs`` (the global state of both in one call: it is row by
        row, so the same values)."""
        if self.cfg.critic in ("global", "role"):
            both = self.critic_input(torch.cat([obs, next_obs]))
            return both[:obs.shape[0]], both[obs.shape[0]:]
        return self.critic_input(obs), self.critic_input(next_obs)

    @torch.no_grad()
    def td_target(self, batch: Sequence[torch.Tensor], next_state: torch.Tensor | None = None) -> torch.Tensor:
        """``y_i = r_i x reward_scale + gamma x Q'_i(S', a'_1 .. a'_N)`` for every agent ``[N, K]`` (with
        twin critics the smaller of the two ``Q'``); a ``batch`` without next actions (4 tensors) bootstraps
        non-learning agents on a zero action. ``next_state``: ``critic_input(next_obs)`` if the caller has it."""
        rew, next_obs = batch[2], batch[3]
        k = next_obs.shape[0]
        next_act = self.target_next_actions(next_obs, batch[4] if len(batch) > 4 else None)
        if next_state is None:
            next_state = self.critic_input(next_obs)
        q_next = self.critics_tgt(next_state, next_act.reshape(k, -1), index=self._critic_ix, slot=self._slot)
        if self.twins > 1:
            q_next = q_next.view(self.twins, self.n_agents, k).amin(0)
        return rew.t() * self.cfg.reward_scale + self.cfg.gamma * q_next

    def target_next_actions(self, next_obs: torch.Tensor, stored: torch.Tensor | None) -> torch.Tensor:
        """Next actions ``[K, N, 2]`` of the TD target: the stored ones where they are known (what a scripted
        agent or a frozen opponent did at ``next_obs``); where they are NaN (unknown, the replay buffer's
        default) or not given, the target actors' for agents that learn (with ``matd3``'s clipped smoothing
        noise) and zero for those that do not (static evaders)."""
        tgt = self.actors_tgt(next_obs.transpose(0, 1), self._actor_ix, self._in_scale, self._in_shift)
        tgt = tgt.transpose(0, 1)
        if self.cfg.algorithm == "matd3":
            c = self.cfg.target_noise_clip
            noise = torch.randn(tgt.shape, generator=self.target_gen, device=self.device) * self.cfg.target_noise
            tgt = (tgt + noise.clamp(-c, c)).clamp(-1.0, 1.0)
        unknown = tgt if self._all_learn else torch.where(self._learns.view(1, -1, 1), tgt, torch.zeros_like(tgt))
        if stored is None:
            return unknown
        return torch.where(torch.isnan(stored), unknown, stored)

    def update(self, batch: Sequence[torch.Tensor], imitation: bool = False,
               imitation_weight: float | None = None) -> dict[str, float]:
        """One critic step, then (every ``policy_delay``-th update with ``matd3``, else always) one actor
        step and a soft target update, for every agent at once. On updates without an actor step the actor
        figures returned are those of the last actor step.

        ``imitation``: the actor step regresses the actors onto the batch's teacher actions instead of
        following the critics (behaviour cloning; the critics learn as always). Otherwise, with
        ``train.imitation_weight`` w > 0, the actor loss is TD3+BC's (Fujimoto and Gu 2021):
        ``-Q / mean|Q| + w x |mu - teacher|^2`` on the rows that have a teacher action (``imitation_weight``
        overrides w, for a decaying weight)."""
        obs, act = batch[0], batch[1]  # [K, N, D], [K, N, 2]
        cfg = self.cfg
        k, n = obs.shape[0], self.n_agents
        state, next_state = self.critic_inputs(obs, batch[3])
        y = self.td_target(batch, next_state)
        feat = self.critics.rows(self.critics.obs_features(state), self._critic_ix, self._slot)  # [T N, K, h1]
        q = self.critics(state, act.reshape(k, -1), feat, self._critic_ix, self._slot)
        y_rows = y if self.twins == 1 else y.repeat(self.twins, 1)
        w_rows = self._weight if self.twins == 1 else self._weight.repeat(self.twins)
        critic_loss_n = (q - y_rows).pow(2).mean(1)  # [T N]
        self.critic_opt.zero_grad(set_to_none=True)
        (critic_loss_n * w_rows).sum().backward()
        critic_norm = clip_grad_norm_per_agent(_params_of(self.critics, self.critic_opt), cfg.grad_clip)
        self.critic_opt.step()
        self.updates += 1
        if cfg.algorithm != "matd3" or self.updates % cfg.policy_delay == 0:
            teach = batch[5] if len(batch) > 5 else None
            w_bc = cfg.imitation_weight if imitation_weight is None else imitation_weight
            self._last_actor = self._actor_step(obs, act, state, feat[:n].detach(), teach, imitation, w_bc)
            soft_update(self.actors_tgt, self.actors, cfg.tau)
            soft_update(self.critics_tgt, self.critics, cfg.tau)
        w = self._mean_w
        return {**self._last_actor, "critic_loss": float((critic_loss_n.detach()[:n] * w).sum()),
                "q_mean": float(q.detach()[:n].mean()), "critic_grad_norm": float(critic_norm.mean())}

    def _actor_step(self, obs: torch.Tensor, act: torch.Tensor, state: torch.Tensor,
                    feat: torch.Tensor, teach: torch.Tensor | None = None,
                    imitation: bool = False, w_bc: float = 0.0) -> dict[str, float]:
        """Critic i (twin 0) sees agent i's action replaced by mu_i(o_i), the others' from the sample (with
        ``imitation``, no critic: the distance to the teacher's actions)."""
        cfg = self.cfg
        k, n = obs.shape[0], self.n_agents
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
            actor_loss_n = bc_n + cfg.action_reg * pre.pow(2).mean((1, 2))
        else:
            joint = act.unsqueeze(0) * (1 - self._eye) + mu.unsqueeze(2) * self._eye  # [N, K, N, 2]
            self.critics.requires_grad_(False)
            try:
                q_pi = self.critics(state, joint.reshape(n, k, -1), feat, self._actor_critic_ix,
                                    None if self._slot is None else self._slot[:n])
            finally:
                self.critics.requires_grad_(True)
            if bc_n is not None:  # TD3+BC: the Q term normalised so that imitation_weight means the same
                q_term = -q_pi.mean(1) / q_pi.detach().abs().mean(1).clamp(min=1e-6)
                actor_loss_n = q_term + w_bc * bc_n
            else:
                actor_loss_n = -q_pi.mean(1)
            actor_loss_n = actor_loss_n + cfg.action_reg * pre.pow(2).mean((1, 2))
        if cfg.int8_robustness > 0:
            robust_n = self.int8_sensitivity(obs.transpose(0, 1))
            actor_loss_n = actor_loss_n + cfg.int8_robustness * robust_n
        self.actor_opt.zero_grad(set_to_none=True)
        (actor_loss_n * self._weight).sum().backward()
        actor_norm = clip_grad_norm_per_agent(_params_of(self.actors, self.actor_opt), cfg.grad_clip)
        self.actor_opt.step()
        w = self._mean_w
        if cfg.int8_robustness > 0:
            extra["int8_sensitivity"] = float((robust_n.detach() * w).sum())
        return {**extra, "actor_loss": float((actor_loss_n.detach() * w).sum()),
                "actor_grad_norm": float(actor_norm.mean())}

    def _bc_loss(self, mu: torch.Tensor, teach: torch.Tensor, obs: torch.Tensor | None = None) -> torch.Tensor:
        """[N] mean squared distance of actions ``mu`` [N, K, 2] to the teacher's ``teach`` [K, N, 2] over the rows
        that have one (NaN: none); with ``train.imitation_near_weight`` and the raw observations ``obs`` [K, N, D],
        a weighted mean in which the rows near a known target weigh that much more."""
        t = teach.transpose(0, 1)  # [N, K, 2]
        has = torch.isfinite(t).all(-1)  # [N, K]
        sq = torch.where(has, (mu - torch.nan_to_num(t)).pow(2).sum(-1), torch.zeros((), device=mu.device))
        if not self._weighted_rows or obs is None:
            return sq.sum(1) / has.sum(1).clamp(min=1)
        w = has * self.near_weights(obs)
        return (sq * w).sum(1) / w.sum(1).clamp(min=1e-12)

    def near_weights(self, obs: torch.Tensor) -> torch.Tensor:
        """[N, K] cloning-row weights of the raw observations ``obs`` [K, N, D]: ``train.imitation_near_weight``
        where agent n sees a known target within ``train.imitation_near_radius`` (agents that observe no targets:
        never), times ``train.imitation_obstacle_weight`` where it is within ``train.imitation_obstacle_radius`` of
        an obstacle's surface (with ``train.imitation_obstacle_walls``: or of a wall); 1 elsewhere."""
        o = obs.transpose(0, 1)  # [N, K, D]
        w = torch.ones(o.shape[:2], dtype=o.dtype, device=o.device)

        def rows(cols: torch.Tensor) -> torch.Tensor:  # [N, K, rows, 3]: each agent's columns ``cols`` [N, rows, 3]
            v = torch.gather(o, 2, cols.unsqueeze(1).expand(-1, o.shape[1], -1, -1).flatten(2))
            return v.view(o.shape[0], o.shape[1], -1, 3)

        if self._near is not None:
            cols, sees = self._near
            v = rows(cols)  # (dx, dy, known) of each target
            r = self.cfg.imitation_near_radius
            near = ((v[..., 0].square() + v[..., 1].square() < r * r) & (v[..., 2] > 0.5)).any(-1) & sees.view(-1, 1)
            w = torch.where(near, self.cfg.imitation_near_weight, w)
        hazard: torch.Tensor | None = None  # [N, K] rows next to an obstacle (or a wall)
        if self._obstacle is not None:
            cols, own = self._obstacle
            v = rows(cols)  # (dx, dy, radius) of each obstacle
            surface = (v[..., 0].square() + v[..., 1].square()).sqrt() - v[..., 2] - own.view(-1, 1, 1)
            hazard = ((surface < self.cfg.imitation_obstacle_radius) & (v[..., 2] > 0)).any(-1)
        if self._walls is not None:
            cols, gap0 = self._walls  # own x, y columns [N, 2]; half width minus own radius [N]
            xy = torch.gather(o, 2, cols.unsqueeze(1).expand(-1, o.shape[1], -1))  # [N, K, 2]
            wall = gap0.view(-1, 1) - xy.abs().amax(-1) < self.cfg.imitation_obstacle_radius
            hazard = wall if hazard is None else hazard | wall
        if hazard is not None:
            w = torch.where(hazard, w * self.cfg.imitation_obstacle_weight, w)
        return w

    def clone_step(self, obs: torch.Tensor, teach: torch.Tensor, only: torch.Tensor | None = None) -> float:
        """One behaviour-cloning step of every actor (no critic, no target update) on observations ``[K, N, D]``
        and the teacher's actions ``[K, N, 2]``; returns the mean squared distance to the teacher before it.
        ``only`` [N] (0/1): the loss counts these agents' rows only (the others' actors get no gradient, though
        Adam's momentum still moves them: ``kept_rows`` keeps them as they were)."""
        cfg = self.cfg
        mask, weight = (self.learn_mask, self._weight) if only is None else \
            (self.learn_mask * only, self._weight * only)
        pre = self.actors.forward_pre(obs.transpose(0, 1), self._actor_ix, self._in_scale, self._in_shift)
        bc_n = self._bc_loss(torch.tanh(pre), teach, obs)
        loss_n = bc_n + cfg.action_reg * pre.pow(2).mean((1, 2))
        self.actor_opt.zero_grad(set_to_none=True)
        (loss_n * weight).sum().backward()
        clip_grad_norm_per_agent(_params_of(self.actors, self.actor_opt), cfg.grad_clip)
        self.actor_opt.step()
        return float((bc_n.detach() * mask).sum() / mask.sum().clamp(min=1))

    @contextlib.contextmanager
    def kept_rows(self, agents: Sequence[int]) -> Iterator[None]:
        """Within the block the actors' weights and Adam moments of the models that serve ``agents`` may change;
        on leaving it they are put back as they were (Adam's step count, one for every model, goes on; cloning
        steps leave the target actors alone). Needs ``FlatAdam`` actors whose every parameter has one row per model
        (``BatchedMLP``)."""
        flat = self.actor_opt.flat
        rows = torch.zeros(self.n_models, dtype=torch.bool, device=self.device)
        rows[[self.model_of[i] for i in agents]] = True
        parts = []
        for p in flat.params:
            if p.shape[0] != self.n_models:
                raise ValueError(f"an actor parameter of shape {tuple(p.shape)} has no row per model "
                                 f"({self.n_models}): kept_rows needs BatchedMLP actors")
            parts.append(rows.view(-1, *([1] * (p.dim() - 1))).expand_as(p).reshape(-1))
        keep = torch.cat(parts)
        if not bool(keep.any()):
            yield
            return
        st = self.actor_opt.opt.state.get(self.actor_opt.param, {})
        moments = {k: v[keep].clone() for k, v in st.items() if k in ("exp_avg", "exp_avg_sq")}
        saved = flat.data[keep].clone()
        try:
            yield
        finally:
            with torch.no_grad():
                flat.data[keep] = saved
                st = self.actor_opt.opt.state.get(self.actor_opt.param, {})
                for k, v in moments.items():
                    if k in st:
                        st[k][keep] = v

    def int8_sensitivity(self, obs: torch.Tensor, worst: float = 0.05) -> torch.Tensor:
        """Per agent [N]: the mean squared change of the actions on ``obs`` [N, K, D] and on K observations
        uniform within each agent's per-field ranges when every hidden layer's weights get uniform noise of
        one int8 step (``max|w| / INT8_QMAX`` per output neuron), plus the mean of the worst ``worst`` share
        of those changes (the C export is judged on its worst observation). With ``obs_scaling`` the noise
        is on the weights before the scaling is folded in (close to, not exactly, the exported int8 step)."""
        n, k, _ = obs.shape
        rand = self._obs_lo + self._obs_span * torch.rand(n, k, obs.shape[2], generator=self.reg_gen,
                                                          device=self.device)
        x = self.actor_input(torch.cat([obs, rand], dim=1))  # [N, 2K, D]
        noisy = x
        layers = self.actors.layers(self._actor_ix)
        last = len(layers) - 1
        for li, (w, b) in enumerate(layers):
            if li < last:
                step = w.detach().abs().amax(dim=1, keepdim=True) / INT8_QMAX  # [N, 1, out]: per output neuron
                w = w + (torch.rand(w.shape, generator=self.reg_gen, device=self.device) - 0.5) * step
            noisy = torch.matmul(noisy, w) + b
            noisy = torch.relu(noisy) if li < last else torch.tanh(noisy)
        change = (noisy - self.actors(x, self._actor_ix)).pow(2).sum(-1)  # [N, 2K]
        top = max(1, int(round(worst * change.shape[1])))
        return change.mean(1) + change.topk(top, dim=1).values.mean(1)

    # --------------------------------------------------------------------------------- persistence
    def to_actors(self) -> list[Actor]:
        """Per-agent ``Actor`` modules with exactly ``spec.obs_dim(role)`` inputs (the export contract): copies
        of the role's model with ``share_params``, the scaling folded into the first layer with
        ``obs_scaling``, so that they take raw observations."""
        index = self.model_of if self.cfg.share_params else None
        if self._in_scale is None:
            return self.actors.to_actors(self.obs_dims, index)
        return self.actors.to_actors(self.obs_dims, index, self._in_scale[:, 0], self._in_shift[:, 0])

    def frozen_actors(self) -> BatchedMLP:
        """Every agent's actor as one frozen module on raw observations ``[N, B, D] -> [N, B, 2]`` (one row per
        agent whatever ``share_params``, the scaling folded in): what an opponent snapshot keeps. Without
        either option that is ``actors`` itself (the caller copies it)."""
        if not self.cfg.share_params and self._in_scale is None:
            return self.actors
        return BatchedMLP.from_actors(self.to_actors(), self.obs_dim).to(self.device).requires_grad_(False)

    def state_dict(self) -> dict[str, Any]:
        return {"actors": self.actors.state_dict(), "critics": self.critics.state_dict(),
                "actors_tgt": self.actors_tgt.state_dict(), "critics_tgt": self.critics_tgt.state_dict(),
                "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
                "updates": self.updates, "reg_gen": self.reg_gen.get_state(),
                "target_gen": self.target_gen.get_state(), "options": self.options(),
                "last_actor": dict(self._last_actor)}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        # absent in checkpoints written before the options: those were trained with every option off
        saved = sd.get("options", {name: TrainConfig.__dataclass_fields__[name].default for name in OPTIONS})
        for name in OPTIONS:  # an option newer than the checkpoint was at its default then
            was = saved.get(name, TrainConfig.__dataclass_fields__[name].default)
            if was != getattr(self.cfg, name):
                raise ValueError(f"this learner state was trained with train.{name} = {was!r}, the "
                                 f"config has {getattr(self.cfg, name)!r}: use the run's own config.toml")
        self.actors.load_state_dict(sd["actors"])
        self.critics.load_state_dict(sd["critics"])
        self.actors_tgt.load_state_dict(sd["actors_tgt"])
        self.critics_tgt.load_state_dict(sd["critics_tgt"])
        # torch keeps the given moment tensors (no copy when dtype and device match): copy them, so that a
        # state dict taken from a live learner is not shared with it
        self.actor_opt.load_state_dict(copy.deepcopy(sd["actor_opt"]))
        self.critic_opt.load_state_dict(copy.deepcopy(sd["critic_opt"]))
        # the config's learning rates, not the saved ones: a fine-tune (--init-from) may set new ones
        for opt, lr in ((self.actor_opt, self.cfg.actor_lr), (self.critic_opt, self.cfg.critic_lr)):
            for group in opt.param_groups:
                group["lr"] = lr
        self.updates = int(sd["updates"])
        for name in ("reg_gen", "target_gen"):  # absent in checkpoints written before these streams
            if name in sd:
                getattr(self, name).set_state(sd[name].cpu() if self.device.type == "cpu" else sd[name])
        self._last_actor = dict(sd.get("last_actor", {}))


def _field_columns(spec: SwarmSpec, field: str, names: tuple[str, str, str]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per agent, the observation columns ``names`` of each row of ``field`` [N, rows, 3] (a role with fewer rows
    repeats its first; one without the field reads column 0), and whether the agent observes ``field`` at all [N]."""
    per: list[list[list[int]]] = []
    for role in spec.roles:
        layout = spec.layout(role)
        if field in layout.names():
            f = layout[field]
            c = [f.columns.index(x) for x in names]
            per.append([[f.start + k * len(f.columns) + j for j in c] for k in range(f.rows)])
        else:
            per.append([])
    t = max((len(p) for p in per), default=0) or 1
    cols = torch.zeros(spec.n_agents, t, 3, dtype=torch.long)
    for i, p in enumerate(per):
        for k, row in enumerate(p):
            cols[i, k] = torch.tensor(row)
        for k in range(len(p), t):
            cols[i, k] = cols[i, 0]
    return cols, torch.tensor([bool(p) for p in per])


def _near_columns(spec: SwarmSpec, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """For ``train.imitation_near_weight``: per agent, the observation columns (dx, dy, known) of each target row
    [N, T, 3], and whether the agent observes targets at all [N] (evaders do not: their rows get 0, unused)."""
    cols, sees = _field_columns(spec, "targets", ("dx", "dy", "known"))
    return cols.to(device), sees.to(device)


def _obstacle_columns(spec: SwarmSpec, device: torch.device) -> tuple[torch.Tensor, torch.Tensor] | None:
    """For ``train.imitation_obstacle_weight``: per agent, the observation columns (dx, dy, radius) of each obstacle
    row [N, O, 3] (every role observes the obstacles, ``spec.layout``), and each agent's own radius [N] [m]; None
    in an arena without obstacles."""
    if all(spec.layout(role)["obstacles"].rows == 0 for role in spec.roles):
        return None
    cols, _ = _field_columns(spec, "obstacles", ("dx", "dy", "radius"))
    own = torch.tensor([float(r) for r in spec.per_agent("radius")])
    return cols.to(device), own.to(device)


def _wall_columns(spec: SwarmSpec, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """For ``train.imitation_obstacle_walls``: per agent, the observation columns of its own x, y [N, 2], and the
    arena's half width minus its radius [N] [m] (its body's gap to the nearest wall is that minus max(|x|, |y|))."""
    cols = torch.tensor([[spec.layout(r)["self_pos"].start + k for k in (0, 1)] for r in spec.roles])
    gap0 = torch.tensor([spec.arena.half_width - float(r) for r in spec.per_agent("radius")])
    return cols.to(device), gap0.to(device)


def _index(rows: Sequence[int], n_models: int, device: torch.device) -> torch.Tensor | None:
    """The row -> model index of a batched call; None where row r is model r (no gather needed)."""
    if list(rows) == list(range(n_models)):
        return None
    return torch.tensor(list(rows), device=device)


# ------------------------------------------------------------------------------------------------
# trained actors as an evaluation policy (training.baselines.Policy)


class ActorsPolicy:
    """Every agent's trained actor, evaluated as one batched module: ``act(obs [B, N, D], env) -> [B, N, 2]``.

    Built from per-agent ``Actor`` modules (``training.checkpoint.load_actors``) or from an exported models
    folder (``OnnxActorsPolicy``). Deterministic: no exploration noise. With ``spec`` (and its avoidance layer
    on) every action passes ``runtime.avoidance``, as on the drone."""

    def __init__(self, actors: Sequence[Actor], obs_dim: int, spec: SwarmSpec | None = None) -> None:
        self.net = BatchedMLP.from_actors(actors, obs_dim)
        self.net.requires_grad_(False)
        self.spec = spec

    @torch.no_grad()
    def act(self, obs: np.ndarray, env: Any = None) -> np.ndarray:
        o = torch.as_tensor(obs, dtype=torch.float32).transpose(0, 1)
        a = self.net(o).transpose(0, 1).numpy().astype(np.float64)
        if self.spec is not None:
            avoid_agents(self.spec, obs, a)
        return a


class OnnxActorsPolicy:
    """The ONNX actors of a models folder (``swarm-export onnx``), through ``runtime.policy``, batched per
    agent: what a drone runs (the avoidance layer included), evaluated on the same episodes as the torch
    actors."""

    def __init__(self, folder: str, spec: SwarmSpec | None = None) -> None:
        from runtime.policy import load_models
        self.manifest, self.policies = load_models(folder, spec)
        self.spec = self.manifest.spec

    def act(self, obs: np.ndarray, env: Any = None) -> np.ndarray:
        out = np.zeros(obs.shape[:2] + (2,))
        for i, pol in enumerate(self.policies):
            out[:, i] = pol.act_batch(obs[:, i, :pol.obs_dim])
        return out
