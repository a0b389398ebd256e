"""Networks: the per-agent actor shared by training and export, and the stacked modules the learner trains.

``Actor``: the export contract. The exporter (``firmware_export.onnx_export``) and the C generator rely on
exactly this structure: ``net.0`` Linear(obs_dim, h1), ReLU, ``net.2`` Linear(h1, h2), ReLU, ``net.4``
Linear(h2, act_dim), Tanh.

``BatchedMLP`` and ``BatchedCritic``: ``M`` independent networks with stacked weights ``[M, in, out]``,
evaluated with one batched matmul per layer. Calls take an optional ``index`` ``[E]`` of model numbers: the
e-th row of the batch is evaluated by model ``index[e]`` (parameter sharing: several agents, one model;
twin critics: two models per agent). Without it, row e is model e (the plain one-model-per-agent path).
"""
from __future__ import annotations

import math
import threading
import weakref
from typing import Sequence

import torch
from torch import nn
from torch.autograd.function import once_differentiable


class Actor(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int = 2, hidden: tuple[int, ...] = (64, 64)) -> None:
        super().__init__()
        self.obs_dim = obs_dim
        self.act_dim = act_dim
        self.hidden = tuple(hidden)
        layers: list[nn.Module] = []
        width = obs_dim
        for h in hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        layers += [nn.Linear(width, act_dim), nn.Tanh()]
        self.net = nn.Sequential(*layers)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs)


def _uniform(shape: tuple[int, ...], bound: float, generator: torch.Generator | None) -> torch.Tensor:
    return (torch.rand(*shape, generator=generator) * 2 - 1) * bound


def _pick(t: torch.Tensor, index: torch.Tensor | None) -> torch.Tensor:
    return t if index is None else t.index_select(0, index)


def shared_matmul(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``x @ w[m]`` for every model m: ``[B, in] x [M, in, out] -> [M, B, out]``, or ``torch.matmul`` when
    ``x`` is per model ``[M, B, in]``. A shared ``x`` goes through one ``[B, in] x [in, M out]`` GEMM instead
    of a batched matmul over M copies of ``x`` (torch's broadcast copies it): the same products and sums,
    several times faster for the critics' wide state input, forward and backward."""
    if x.dim() != 2:
        return torch.matmul(x, w)
    m, n_in, n_out = w.shape
    y = torch.mm(x, w.permute(1, 0, 2).reshape(n_in, m * n_out))
    return y.view(x.shape[0], m, n_out).transpose(0, 1)


NARROW = 16
"""Output widths up to this are multiplied transposed by ``shared_linear``: a batched ``[B, in] x [in, out]``
with a handful of outputs (an actor's 2 actions, a role critic's heads) runs several times slower than the same
products as ``[out, in] x [in, B]`` in torch 2.13's CPU GEMM (measured 240 against 40 us for 12 x 256 x 64 x 2)."""


def shared_linear(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``shared_matmul(x, w) + b`` (``b`` ``[M, 1, out]``) with the bias added by the GEMM itself (``addmm`` /
    ``baddbmm``): one op and one output instead of two; the same sums up to float rounding."""
    m, n_in, n_out = w.shape
    if x.dim() != 2:
        if n_out <= NARROW:
            return _NarrowLinear.apply(x, w, b)
        return torch.baddbmm(b, x, w)
    y = torch.addmm(b.reshape(m * n_out), x, w.permute(1, 0, 2).reshape(n_in, m * n_out))
    # contiguous per model: the ReLU's backward then reads its output and gradient in one layout (elementwise
    # kernels on mismatched strides ran several times slower than this copy)
    return y.view(x.shape[0], m, n_out).transpose(0, 1).contiguous()


class _NarrowLinear(torch.autograd.Function):
    """``x @ w + b`` for a narrow output ``[E, B, in] x [E, in, out] -> [E, B, out]``, every GEMM (forward and
    backward) in the orientation torch 2.13's CPU GEMM runs fast: the output as ``(w^T x^T)^T``, the weight's
    gradient as ``(g^T x)^T``; the input's gradient ``g w^T`` comes out contiguous like ``x`` (the ReLU's
    backward before it runs on matching layouts)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(x, w)
        ctx.b_shape = b.shape
        # a copy (of a narrow output: cheap), not a view, so that a ReLU may work on it in place
        return torch.baddbmm(b.transpose(1, 2), w.transpose(1, 2), x.transpose(1, 2)).transpose(1, 2).contiguous()

    @staticmethod
    def backward(ctx, g: torch.Tensor):  # type: ignore[override]
        x, w = ctx.saved_tensors
        gx = gw = gb = None
        if ctx.needs_input_grad[0]:
            gx = torch.bmm(g, w.transpose(1, 2))
        if ctx.needs_input_grad[1]:
            gw = torch.bmm(g.transpose(1, 2), x).transpose(1, 2)
        if ctx.needs_input_grad[2]:
            gb = g.sum(1, keepdim=True).sum_to_size(ctx.b_shape)
        return gx, gw, gb


POOLED = True
"""``BatchedMLP.forward_pre`` runs per-row inputs through ``_PooledMLP`` (False: layer by layer through
``shared_linear``, which computes the same values bit for bit)."""


class _BufferPool:
    """Tensors to reuse, by shape: what ``take`` hands out is not handed out again until it is given back. A
    fresh ``[12, 256, 64]`` activation (786 kB) costs its first touch of new memory pages (glibc hands freed
    blocks that large back to the system): 127-162 page faults per learner update without the pool, 0.2-0.7 with
    it; a cloning step's 3 MB activations more (BENCHMARKS.md, Learner)."""

    MAX_SHAPES = 16
    """Shapes kept at most (the oldest dropped first): a caller whose batch size changes at every call does not
    grow the pool without bound."""
    MAX_PER_SHAPE = 8
    """Free tensors kept at most per shape (an update holds 4 of the actors' hidden shape at once)."""

    def __init__(self) -> None:
        self._free: dict[tuple, list[torch.Tensor]] = {}  # (shape, dtype, device) -> free tensors
        self._lock = threading.Lock()

    def take(self, shape: tuple[int, ...], like: torch.Tensor) -> torch.Tensor:
        if not torch.is_inference_mode_enabled():  # (a tensor made in inference mode cannot serve outside it)
            with self._lock:
                free = self._free.get((shape, like.dtype, like.device))
                if free:
                    return free.pop()
        return torch.empty(shape, dtype=like.dtype, device=like.device)

    def give(self, t: torch.Tensor) -> None:
        if t.is_inference():
            return
        key = (tuple(t.shape), t.dtype, t.device)
        with self._lock:
            if key not in self._free and len(self._free) >= self.MAX_SHAPES:
                del self._free[next(iter(self._free))]
            free = self._free.setdefault(key, [])
            if len(free) < self.MAX_PER_SHAPE:
                free.append(t)


_POOLS: "weakref.WeakKeyDictionary[nn.Module, _BufferPool]" = weakref.WeakKeyDictionary()
_POOLS_LOCK = threading.Lock()


def _pool_of(module: nn.Module) -> _BufferPool:
    """The module's buffer pool (kept beside it, not in it: a deep copy or a pickle of the module has none)."""
    with _POOLS_LOCK:
        pool = _POOLS.get(module)
        if pool is None:
            pool = _POOLS[module] = _BufferPool()
        return pool


class _PooledMLP(torch.autograd.Function):
    """``BatchedMLP.forward_pre`` on a per-row input ``[E, B, in]``, weights and biases per row
    (``layers(index)``), as one autograd node. Every product is the one ``shared_linear`` and autograd would
    compute (``baddbmm`` with the bias, ``_NarrowLinear``'s orientation for narrow outputs; backward: the
    input's gradient ``g w^T``, the weight's ``x^T g``, the bias's ``g`` summed over the batch, ReLU's
    ``threshold_backward``), so the results are equal bit for bit; what differs is where they are written. The
    hidden activations (wide layers) are written into buffers of the module's pool, kept until the backward
    pass (or given back at once when no gradient is wanted), and the backward pass's hidden gradients too.
    Only the output and the returned gradients are fresh tensors. A second backward pass through the same
    graph (``retain_graph``) is refused: its activations may have been reused."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, pool: _BufferPool, grad: bool,  # type: ignore[override]
                in_scale: torch.Tensor | None, in_shift: torch.Tensor | None, *wb: torch.Tensor) -> torch.Tensor:
        ws, bs = wb[0::2], wb[1::2]
        last = len(ws) - 1
        pooled: list[torch.Tensor] = []
        h = x
        if in_scale is not None:  # x * in_scale + in_shift, as two operations (the same rounding)
            h = torch.mul(x, in_scale, out=pool.take(tuple(x.shape), x)).add_(in_shift)
            pooled.append(h)
        hs = [h]  # the input of every layer
        for k in range(last + 1):
            w, b = ws[k], bs[k]
            if w.shape[2] <= NARROW:  # as _NarrowLinear
                h = torch.baddbmm(b.transpose(1, 2), w.transpose(1, 2), h.transpose(1, 2)).transpose(1, 2)
                h = h.contiguous()
            else:
                out = pool.take((h.shape[0], h.shape[1], w.shape[2]), h)
                h = torch.baddbmm(b, h, w, out=out)
                if k < last:
                    pooled.append(out)
            if k < last:
                h = h.relu_()
                hs.append(h)
        if grad:  # the weights saved as such (autograd checks them for in-place changes), the layers' inputs
            ctx.save_for_backward(in_scale, *ws)  # (ours, or the caller's x) kept as they are
            ctx.hidden, ctx.pool, ctx.pooled = hs, pool, pooled
            ctx.b_shapes = [b.shape for b in bs]
            ctx.done = False
        else:
            for t in pooled:
                pool.give(t)
        return h

    @staticmethod
    @once_differentiable
    def backward(ctx, g: torch.Tensor):  # type: ignore[override]
        if ctx.done:
            raise RuntimeError("_PooledMLP: a second backward pass through the same graph (retain_graph) is not "
                               "supported: its activations may have been reused; set networks.POOLED = False")
        ctx.done = True
        in_scale, *ws = ctx.saved_tensors
        hs, pool = ctx.hidden, ctx.pool
        need = ctx.needs_input_grad  # x, pool, grad, in_scale, in_shift, w0, b0, w1, b1, ...
        if need[3] or need[4]:
            raise RuntimeError("_PooledMLP: no gradient to in_scale or in_shift (constants of the input scaling)")
        last = len(ws) - 1
        grads: list[torch.Tensor | None] = [None] * (2 * len(ws))
        for k in range(last, -1, -1):
            w, xin = ws[k], hs[k]
            if k < last:  # g: the gradient at this layer's ReLU output, a pool buffer of ours: in place
                y = hs[k + 1]
                g = torch.ops.aten.threshold_backward.grad_input(g, y, 0, grad_input=g)
            if w.shape[2] <= NARROW:  # as _NarrowLinear.backward
                grads[2 * k] = torch.bmm(g.transpose(1, 2), xin).transpose(1, 2)
            else:  # as autograd's baddbmm
                grads[2 * k] = torch.bmm(xin.transpose(1, 2), g)
            grads[2 * k + 1] = g.sum(1, keepdim=True).sum_to_size(ctx.b_shapes[k])
            if k > 0:  # the gradient at a hidden layer's output: into a pool buffer, never returned
                nxt = torch.bmm(g, w.transpose(1, 2), out=pool.take(tuple(xin.shape), xin))
            elif need[0]:  # the input's gradient, returned: a tensor of its own
                nxt = torch.bmm(g, w.transpose(1, 2))
                if in_scale is not None:
                    nxt = nxt.mul_(in_scale)
            else:
                nxt = None
            if k < last:
                pool.give(g)
            g = nxt
        for t in ctx.pooled:  # the activations, read for the last time above
            pool.give(t)
        ctx.hidden = ctx.pooled = None
        return (g, None, None, None, None, *grads)


class BatchedMLP(nn.Module):
    """``n_models`` independent MLPs evaluated together: ``[E, B, in] -> [E, B, out]`` (``E = n_models``, or
    ``len(index)``).

    Layer k has weight ``[M, in_k, out_k]`` and bias ``[M, 1, out_k]``; hidden layers use ReLU, the output
    layer ``out_act`` ("tanh" or "none"). ``forward`` also accepts an input shared by all rows ``[B, in]``.
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
            self.weights.append(nn.Parameter(_uniform((n_models, fan_in, fan_out), bound, generator)))
            self.biases.append(nn.Parameter(_uniform((n_models, 1, fan_out), bound, generator)))

    def tensors(self) -> tuple[list[nn.Parameter], list[nn.Parameter]]:
        """The layers' weights and biases (read from the ``ParameterList``s' own dicts: iterating one indexes
        it item by item in Python, a noticeable share of a small learner update)."""
        return list(self.weights._parameters.values()), list(self.biases._parameters.values())

    def layers(self, index: torch.Tensor | None = None) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(weight ``[E, in, out]``, bias ``[E, 1, out]``) per layer, rows picked by ``index``."""
        ws, bs = self.tensors()
        if index is None:
            return list(zip(ws, bs))
        return [(w.index_select(0, index), b.index_select(0, index)) for w, b in zip(ws, bs)]

    def forward_pre(self, x: torch.Tensor, index: torch.Tensor | None = None, in_scale: torch.Tensor | None = None,
                    in_shift: torch.Tensor | None = None) -> torch.Tensor:
        """Output before the output activation. ``in_scale``, ``in_shift`` ``[E, 1, in]`` (both or neither): the
        rows see ``x * in_scale + in_shift``. A per-row input ``[E, B, in]`` goes through ``_PooledMLP`` (the
        same products, its scaled input, hidden activations and their gradients in buffers reused from call to
        call)."""
        if x.dim() == 3 and POOLED:
            wb = [t for pair in self.layers(index) for t in pair]
            grad = torch.is_grad_enabled() and (x.requires_grad or any(t.requires_grad for t in wb))
            return _PooledMLP.apply(x, _pool_of(self), grad, in_scale, in_shift, *wb)
        if in_scale is not None:
            x = x * in_scale + in_shift
        layers = self.layers(index)
        last = len(layers) - 1
        for k, (w, b) in enumerate(layers):
            x = shared_linear(x, w, b)  # a [B, in] input is shared by the E rows
            if k < last:
                x = x.relu_()  # in place: relu's backward reads its output, which nothing else holds
        return x

    def forward(self, x: torch.Tensor, index: torch.Tensor | None = None, in_scale: torch.Tensor | None = None,
                in_shift: torch.Tensor | None = None) -> torch.Tensor:
        y = self.forward_pre(x, index, in_scale, in_shift)
        return torch.tanh(y) if self.out_act == "tanh" else y

    # -- the per-agent Actor contract -----------------------------------------------------------------
    def to_actors(self, in_dims: Sequence[int], index: Sequence[int] | None = None,
                  in_scale: torch.Tensor | None = None, in_shift: torch.Tensor | None = None) -> list[Actor]:
        """Per-agent ``Actor(in_dims[i])`` with the weights of model ``index[i]`` (default i); the first layer
        keeps only the first ``in_dims[i]`` input columns (the rest only ever saw zero padding). With
        ``in_scale``/``in_shift`` ``[len(in_dims), in]`` the model sees ``x * in_scale + in_shift``, which is
        folded into the first layer: ``W' = diag(in_scale) W``, ``b' = b + in_shift W``."""
        if self.out_act != "tanh":
            raise ValueError("only a tanh-output BatchedMLP is an actor")
        hidden = tuple(self.widths[1:-1])
        out = []
        for i, d in enumerate(in_dims):
            m = i if index is None else int(index[i])
            actor = Actor(int(d), self.widths[-1], hidden)
            sd = {}
            for k, (w, b) in enumerate(zip(self.weights, self.biases)):
                wi = w[m].detach().cpu()
                bi = b[m, 0].detach().cpu()
                if k == 0:
                    if in_scale is not None:
                        scale, shift = in_scale[i].detach().cpu(), in_shift[i].detach().cpu()
                        # float64 for the fold, so that it adds no error beyond float32's rounding
                        bi = (bi.double() + shift.double() @ wi.double()).float()
                        wi = (scale.double()[:, None] * wi.double()).float()
                    wi = wi[:d]
                sd[f"net.{2 * k}.weight"] = wi.t().contiguous().clone()
                sd[f"net.{2 * k}.bias"] = bi.clone()
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
    """``n_models`` centralized critics ``Q(S, A)``: S a critic input shared by every row ``[B, state_in]``
    (all observations, or the global state), A the joint action ``[B, act_in]`` (or per row ``[E, B, ...]``);
    returns ``[E, B]``. The first layer is split into its state and action parts so that the (large, shared)
    state part is multiplied once per model, not per action variant nor per agent sharing the model.

    ``n_slots`` > 0 adds a one-hot input of that size (which agent of a shared model is evaluated: ``slot``
    ``[E]``), kept as its weight rows ``w_id`` ``[M, n_slots, h1]``."""

    def __init__(self, n_models: int, obs_in: int, act_in: int, hidden: Sequence[int],
                 generator: torch.Generator | None = None, n_slots: int = 0) -> None:
        super().__init__()
        h1 = hidden[0]
        bound = 1.0 / math.sqrt(obs_in + act_in + n_slots)
        self.w_obs = nn.Parameter(_uniform((n_models, obs_in, h1), bound, generator))
        self.w_act = nn.Parameter(_uniform((n_models, act_in, h1), bound, generator))
        self.b1 = nn.Parameter(_uniform((n_models, 1, h1), bound, generator))
        self.rest = BatchedMLP(n_models, h1, hidden[1:], 1, "none", generator)
        self.n_slots = n_slots
        if n_slots:
            self.w_id = nn.Parameter(_uniform((n_models, n_slots, h1), bound, generator))

    def obs_features(self, obs_flat: torch.Tensor) -> torch.Tensor:
        """The state part of the first layer, per model ``[M, B, h1]``."""
        return shared_matmul(obs_flat, self.w_obs) + self.b1

    def rows(self, feat: torch.Tensor, index: torch.Tensor | None = None,
             slot: torch.Tensor | None = None) -> torch.Tensor:
        """Per-model features ``[M, B, h1]`` -> per evaluated row ``[E, B, h1]`` (plus the row's one-hot)."""
        if index is None:
            return feat
        out = feat.index_select(0, index)
        if self.n_slots:
            out = out + self.w_id[index, slot].unsqueeze(1)
        return out

    def forward(self, obs_flat: torch.Tensor, act_joint: torch.Tensor, obs_feat: torch.Tensor | None = None,
                index: torch.Tensor | None = None, slot: torch.Tensor | None = None) -> torch.Tensor:
        """``obs_feat``: ``rows(obs_features(obs_flat), index, slot)`` when the caller has it already."""
        if obs_feat is None:
            obs_feat = self.rows(self.obs_features(obs_flat), index, slot)
        h = torch.relu(obs_feat + shared_matmul(act_joint, _pick(self.w_act, index)))
        return self.rest(h, index).squeeze(-1)
