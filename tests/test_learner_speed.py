"""The learner's speed-ups (issue 13) compute the same updates: ``training.networks.shared_linear`` (bias added by
the GEMM, narrow outputs multiplied transposed, ReLU in place), the role critics' split first layer in the actor
step (``RoleCritics.forward_split``) and the cached columns of ``training.maddpg.global_state``, checked against
the straightforward forms written out here, over several updates of every learner path (critic step, actor step
with and without TD3+BC, imitation update, cloning step)."""
from __future__ import annotations

from typing import Any

import pytest
import torch

from training import maddpg, networks, rolecritic
from training.config import ExperimentConfig
from training.rolecritic import make_learner

VARIANTS = {
    "shipped": {"critic": "role", "share_params": True, "obs_scaling": True, "imitation_weight": 1.0, "teacher": "classical",
                "critic_hidden": [32, 32]},
    "default": {},
    "global_matd3": {"critic": "global", "algorithm": "matd3", "policy_delay": 2},
    "local_shared_int8": {"share_params": True, "int8_robustness": 0.1},
    "role_matd3": {"critic": "role", "algorithm": "matd3", "policy_delay": 1},
}


def _reference_forward_split(self, state, act):
    """``RoleCritics.forward_split`` as one MLP call on the concatenated input, rows picked by model number."""
    e, k = act.shape[0], act.shape[1]
    x = torch.cat([state.unsqueeze(0).expand(e, k, state.shape[1]), act], dim=2)
    self.requires_grad_(False)  # the gradient to the actions only
    try:
        return self.mlp(x, torch.arange(e))
    finally:
        self.requires_grad_(True)


def _reference_forward_pre(self, x, index=None, in_scale=None, in_shift=None):
    """``BatchedMLP.forward_pre`` as written before the speed-ups: the input scaled, then per layer matmul, bias,
    ReLU."""
    if in_scale is not None:
        x = x * in_scale + in_shift
    layers = self.layers(index)
    for k, (w, b) in enumerate(layers):
        x = networks.shared_matmul(x, w) + b
        if k < len(layers) - 1:
            x = torch.relu(x)
    return x


def _reference_global_state(spec, obs):
    """``global_state`` with its columns looked up from the spec's layouts on every call."""
    k, n = obs.shape[0], obs.shape[1]
    cols = []
    for role in spec.roles:
        lay = spec.layout(role)
        cols.append([lay["self_pos"].start, lay["self_pos"].start + 1, lay["self_vel"].start,
                     lay["self_vel"].start + 1])
    pv = torch.gather(obs, 2, torch.tensor(cols).unsqueeze(0).expand(k, n, 4))
    ob = spec.layout(spec.roles[0])["obstacles"]
    o = obs[:, 0, ob.slice].reshape(k, ob.rows, 3)
    centre = o[..., :2] + pv[:, :1, :2]
    obst = torch.cat([centre, o[..., 2:]], dim=-1)
    obst = torch.gather(obst, 1, centre[..., 0].argsort(dim=1).unsqueeze(-1).expand(k, ob.rows, 3))
    return torch.cat([pv[..., :2].reshape(k, -1), pv[..., 2:].reshape(k, -1), obst.reshape(k, -1)], dim=1)


def _config(variant: str) -> ExperimentConfig:
    return ExperimentConfig.from_dict({"name": "t", "spec": {"team": {"n_pursuers": 3, "n_scouts": 2,
                                                                     "n_evaders": 1}},
                                      "train": {"batch_size": 48, "threads": 1, **VARIANTS[variant]}})


def _run(cfg: ExperimentConfig) -> tuple[list[dict[str, float]], dict[str, torch.Tensor], Any]:
    """Four updates (the third an imitation update) and one cloning step from the same seed and batches;
    the losses returned, every learned tensor after them and the learner."""
    agent = make_learner(cfg.spec, cfg.train)
    n, d, k = cfg.spec.n_agents, cfg.spec.max_obs_dim, 48
    g = torch.Generator().manual_seed(3)
    out = []
    for step in range(4):
        teach = torch.rand(k, n, 2, generator=g) * 2 - 1
        teach[::3] = float("nan")  # rows without a teacher action
        next_act = torch.full((k, n, 2), float("nan"))
        next_act[:, -1] = torch.rand(k, 2, generator=g)  # one agent's next action known
        batch = (torch.randn(k, n, d, generator=g), torch.rand(k, n, 2, generator=g) * 2 - 1,
                 torch.randn(k, n, generator=g), torch.randn(k, n, d, generator=g), next_act, teach)
        out.append(agent.update(batch, imitation=step == 2))
    obs, teach = torch.randn(2 * k, n, d, generator=g), torch.rand(2 * k, n, 2, generator=g) * 2 - 1
    out.append({"clone_mse": agent.clone_step(obs, teach)})
    tensors = {}
    for name in ("actors", "critics", "actors_tgt", "critics_tgt"):
        tensors.update({f"{name}.{key}": v.detach().clone() for key, v in getattr(agent, name).state_dict().items()})
    return out, tensors, agent


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_updates_equal_the_straightforward_forms(variant, monkeypatch):
    torch.set_num_threads(1)
    cfg = _config(variant)
    fast_losses, fast, _ = _run(cfg)
    with monkeypatch.context() as m:
        m.setattr(networks.BatchedMLP, "forward_pre", _reference_forward_pre)
        m.setattr(maddpg, "global_state", _reference_global_state)
        m.setattr(rolecritic, "global_state", _reference_global_state)
        m.setattr(rolecritic.RoleCritics, "forward_split", _reference_forward_split)
        ref_losses, ref, _ = _run(cfg)
    assert len(fast_losses) == len(ref_losses) == 5
    for got, want in zip(fast_losses, ref_losses):
        assert got.keys() == want.keys()
        for key in want:
            assert got[key] == pytest.approx(want[key], rel=1e-5, abs=1e-6), key
    assert fast.keys() == ref.keys()
    # Adam moves a weight by up to lr (1e-3) whatever its gradient's size: on an element whose gradient is near
    # zero a float-level difference in the gradient can shift the step by a few 1e-6 (measured 1.4e-6 on one
    # element of 7488 in "shipped"), so the weights get 2 % of one step as absolute tolerance; the losses above
    # are held to 1e-5 relative
    for key in ref:
        torch.testing.assert_close(fast[key], ref[key], rtol=1e-5, atol=2e-5, msg=key)
    # the updates did move the weights (a comparison of untouched tensors would prove nothing)
    init = make_learner(cfg.spec, cfg.train)
    assert not torch.equal(init.actors.weights[0], fast["actors.weights.0"])
    assert not torch.equal(init.critics.state_dict()[next(iter(init.critics.state_dict()))],
                           fast[f"critics.{next(iter(init.critics.state_dict()))}"])


def test_shared_linear_narrow_and_wide_outputs_and_their_gradients_equal_matmul_plus_bias():
    g = torch.Generator().manual_seed(0)
    for out in (2, networks.NARROW, networks.NARROW + 1, 64):
        for shared in (False, True):
            w, b = torch.randn(4, 9, out, generator=g), torch.randn(4, 1, out, generator=g)
            x = torch.randn(33, 9, generator=g) if shared else torch.randn(4, 33, 9, generator=g)
            grad = torch.randn(4, 33, out, generator=g)
            got, want = [], []
            for f, into in ((networks.shared_linear, got), (lambda x, w, b: torch.matmul(x, w) + b, want)):
                xr, wr, br = (t.clone().requires_grad_(True) for t in (x, w, b))
                y = f(xr, wr, br)
                y.backward(grad)
                into += [y.detach(), xr.grad, wr.grad, br.grad]
            for a, e, name in zip(got, want, ("y", "dx", "dw", "db")):
                torch.testing.assert_close(a, e, rtol=1e-5, atol=1e-5, msg=f"{name}, out={out}, shared={shared}")


# ---- the pooled MLP and the flat parameters: the same values bit for bit ------------------------------------
def _mlp_and_grads(mlp, x, index, scale, shift, grad_out, pooled, monkeypatch):
    """(output, x's gradient, every parameter's gradient) of ``mlp.forward_pre`` with ``networks.POOLED``."""
    monkeypatch.setattr(networks, "POOLED", pooled)
    mlp.zero_grad(set_to_none=True)
    xr = x.detach().clone().requires_grad_(x.requires_grad)
    y = mlp.forward_pre(xr, index, scale, shift)
    y.backward(grad_out)
    return [y.detach(), xr.grad, *[p.grad.clone() for p in mlp.parameters()]]


@pytest.mark.parametrize("hidden,out", [((64, 64), 2), ((8, 64), 1), ((64,), 20), ((24, 12, 40), 5)])
@pytest.mark.parametrize("shared,scaled,x_grad", [(False, False, False), (True, True, False), (True, False, True),
                                                  (False, True, True)])
def test_pooled_mlp_equals_layer_by_layer_bit_for_bit(hidden, out, shared, scaled, x_grad, monkeypatch):
    """``_PooledMLP`` (every width path: narrow hidden layers, a wide output, rows picked by an index, the input
    scaling, an input that needs its gradient) against ``shared_linear`` layer by layer and autograd."""
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(1)
    mlp = networks.BatchedMLP(3, 9, hidden, out, "none", g)
    index = torch.tensor([0, 0, 1, 2, 2]) if shared else None
    e = 5 if shared else 3
    x = torch.randn(e, 33, 9, generator=g).requires_grad_(x_grad)
    scale = torch.rand(e, 1, 9, generator=g) + 0.5 if scaled else None
    shift = torch.randn(e, 1, 9, generator=g) if scaled else None
    grad_out = torch.randn(e, 33, out, generator=g)
    for _ in range(2):  # the second time on buffers the pool hands out again
        got = _mlp_and_grads(mlp, x, index, scale, shift, grad_out, True, monkeypatch)
        want = _mlp_and_grads(mlp, x, index, scale, shift, grad_out, False, monkeypatch)
        for name, a, b in zip(["y", "dx"] + [n for n, _ in mlp.named_parameters()], got, want):
            if b is None:
                assert a is None and name == "dx" and not x_grad, name
            else:
                assert torch.equal(a, b), name


def test_pooled_buffers_are_not_handed_out_while_a_graph_holds_them():
    """Two graphs alive at once, a no-grad call and a graph never backpropagated in between: each backward pass
    still reads its own activations (the gradients equal those of separate modules that share nothing)."""
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(2)
    mlp = networks.BatchedMLP(2, 6, (32, 32), 2, "tanh", g)
    xs = [torch.randn(2, 17, 6, generator=g) for _ in range(4)]

    def grads_alone(x):
        fresh = networks.BatchedMLP(2, 6, (32, 32), 2, "tanh")
        fresh.load_state_dict(mlp.state_dict())
        fresh(x).square().sum().backward()
        return [p.grad.clone() for p in fresh.parameters()]

    want = [grads_alone(x) for x in xs[:2]]
    y0 = mlp(xs[0]).square().sum()
    y1 = mlp(xs[1]).square().sum()
    with torch.no_grad():
        mlp(xs[2])  # takes and gives back buffers while y0's and y1's are held
    mlp(xs[3]).square().sum()  # a graph dropped without backward: its buffers are simply not given back
    for y, w in ((y1, want[1]), (y0, want[0])):  # backward in the other order
        mlp.zero_grad(set_to_none=True)
        y.backward()
        for p, expect in zip(mlp.parameters(), w):
            assert torch.equal(p.grad, expect)


def test_pooled_mlp_refuses_a_second_backward_through_one_graph():
    mlp = networks.BatchedMLP(1, 4, (32,), 2, "none")
    y = mlp(torch.randn(1, 5, 4)).sum()
    y.backward(retain_graph=True)
    with pytest.raises(RuntimeError, match="second backward pass"):
        y.backward()


def test_pool_keeps_a_bounded_number_of_tensors():
    pool = networks._BufferPool()
    like = torch.zeros(1)
    for n in range(pool.MAX_SHAPES + 5):
        for _ in range(pool.MAX_PER_SHAPE + 3):
            pool.give(torch.empty(n + 1, 2))
    assert len(pool._free) == pool.MAX_SHAPES
    assert all(len(v) == pool.MAX_PER_SHAPE for v in pool._free.values())
    assert pool.take((pool.MAX_SHAPES + 5, 2), like).shape == (pool.MAX_SHAPES + 5, 2)  # kept: the newest
    with torch.inference_mode():  # never hands out, nor keeps, an inference-mode tensor
        t = pool.take((pool.MAX_SHAPES + 5, 2), like)
        assert t.is_inference()
        pool.give(t)
    assert not any(x.is_inference() for v in pool._free.values() for x in v)


@pytest.mark.parametrize("variant", ["shipped", "default", "role_matd3"])
def test_flat_adam_and_pooled_mlp_train_bit_for_bit_like_per_tensor_adam(variant, monkeypatch):
    """The learner as it runs (``FlatAdam`` on flat parameters, one-call soft updates, ``_PooledMLP``) gives
    exactly the weights, losses and Adam moments of per-tensor fused Adam, per-tensor soft updates and the
    layer-by-layer MLP; its optimizer ``state_dict`` has that optimizer's layout, and each loads the other's."""
    torch.set_num_threads(1)
    cfg = _config(variant)
    fast_losses, fast, fast_agent = _run(cfg)
    with monkeypatch.context() as m:  # per-tensor fused Adam, per-tensor soft updates, layer by layer
        m.setattr(networks, "POOLED", False)
        m.setattr(maddpg, "adam", lambda online, lr, target=None: torch.optim.Adam(online.parameters(), lr=lr,
                                                                                 fused=True))
        ref_losses, ref, ref_agent = _run(cfg)
    assert isinstance(fast_agent.actor_opt, maddpg.FlatAdam) and isinstance(ref_agent.actor_opt, torch.optim.Adam)
    fast_sd, ref_sd = fast_agent.state_dict(), ref_agent.state_dict()
    assert fast_losses == ref_losses
    assert fast.keys() == ref.keys() and all(torch.equal(fast[key], ref[key]) for key in ref)
    for opt in ("actor_opt", "critic_opt"):
        a, b = fast_sd[opt], ref_sd[opt]
        assert a["param_groups"] == b["param_groups"]
        assert a["state"].keys() == b["state"].keys() and len(a["state"]) > 0
        for i in b["state"]:
            assert a["state"][i].keys() == b["state"][i].keys()
            assert all(torch.equal(a["state"][i][key], b["state"][i][key]) for key in b["state"][i])
    # each state loads into the other kind of learner, and all four continue with the same update
    flat_from_ref = make_learner(cfg.spec, cfg.train)
    flat_from_ref.load_state_dict(ref_sd)
    with monkeypatch.context() as m:
        m.setattr(networks, "POOLED", False)
        m.setattr(maddpg, "adam", lambda online, lr, target=None: torch.optim.Adam(online.parameters(), lr=lr,
                                                                                 fused=True))
        ref_from_flat = make_learner(cfg.spec, cfg.train)
    ref_from_flat.load_state_dict(fast_sd)
    n, d, k = cfg.spec.n_agents, cfg.spec.max_obs_dim, 48
    g = torch.Generator().manual_seed(9)
    batch = (torch.randn(k, n, d, generator=g), torch.rand(k, n, 2, generator=g) * 2 - 1,
             torch.randn(k, n, generator=g), torch.randn(k, n, d, generator=g), torch.full((k, n, 2), float("nan")))
    after = []
    for agent in (fast_agent, ref_agent, flat_from_ref, ref_from_flat):
        agent.update(batch)
        after.append(torch.cat([p.detach().reshape(-1) for p in (*agent.actors.parameters(),
                                                                 *agent.critics.parameters())]))
    assert all(torch.equal(after[0], other) for other in after[1:])


def test_flat_adam_takes_back_a_replaced_gradient_and_refuses_a_moved_parameter():
    mlp = networks.BatchedMLP(2, 3, (4,), 2, "none")
    opt = maddpg.FlatAdam(mlp, 0.1)
    before = [p.detach().clone() for p in mlp.parameters()]
    opt.zero_grad()
    mlp.weights[0].grad = torch.ones_like(mlp.weights[0])  # replaced, not accumulated into the buffer
    opt.step()
    moved = [not torch.equal(p, b) for p, b in zip(mlp.parameters(), before)]
    assert moved == [True, False, False, False]  # the replaced gradient was taken; zero elsewhere
    mlp.weights[0].data = torch.zeros_like(mlp.weights[0])
    with pytest.raises(RuntimeError, match="replaced"):
        opt.step()
