"""The learner's speed-ups (issue 13) compute the same updates: ``training.networks.shared_linear`` (bias added by
the GEMM, narrow outputs multiplied transposed, ReLU in place), the role critics' split first layer in the actor
step (``RoleCritics.forward_split``) and the cached columns of ``training.maddpg.global_state``, checked against
the straightforward forms written out here, over several updates of every learner path (critic step, actor step
with and without TD3+BC, imitation update, cloning step)."""
from __future__ import annotations

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
    return self.mlp(x, torch.arange(e))


def _reference_forward_pre(self, x, index=None):
    """``BatchedMLP.forward_pre`` as written before the speed-ups: matmul, then bias, then ReLU."""
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


def _run(cfg: ExperimentConfig) -> tuple[list[dict[str, float]], dict[str, torch.Tensor]]:
    """Four updates (the third an imitation update) and one cloning step from the same seed and batches;
    the losses returned and every learned tensor after them."""
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
    return out, tensors


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_updates_equal_the_straightforward_forms(variant, monkeypatch):
    torch.set_num_threads(1)
    cfg = ExperimentConfig.from_dict({"name": "t", "spec": {"team": {"n_pursuers": 3, "n_scouts": 2,
                                                                     "n_evaders": 1}},
                                      "train": {"batch_size": 48, "threads": 1, **VARIANTS[variant]}})
    fast_losses, fast = _run(cfg)
    with monkeypatch.context() as m:
        m.setattr(networks.BatchedMLP, "forward_pre", _reference_forward_pre)
        m.setattr(maddpg, "global_state", _reference_global_state)
        m.setattr(rolecritic, "global_state", _reference_global_state)
        m.setattr(rolecritic.RoleCritics, "forward_split", _reference_forward_split)
        ref_losses, ref = _run(cfg)
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
