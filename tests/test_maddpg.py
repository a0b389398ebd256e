"""training.maddpg: batched actors/critics, replay buffer, per-agent clipping, masked (static) agents."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from runtime.spec import Role
from training.config import ExperimentConfig, TrainConfig
from training.maddpg import MADDPG, ActorsPolicy, BatchedMLP, ReplayBuffer, clip_grad_norm_per_agent


def _cfg(**train) -> ExperimentConfig:
    return ExperimentConfig.from_dict({"name": "t", "spec": {"team": {"n_pursuers": 2, "n_scouts": 1,
                                                                      "n_evaders": 1}},
                                       "train": {"batch_size": 16, "buffer_size": 64, "threads": 1, **train}})


def test_batched_actors_match_the_per_agent_actors_they_export():
    cfg = _cfg()
    agent = MADDPG(cfg.spec, cfg.train)
    actors = agent.to_actors()
    assert [a.obs_dim for a in actors] == [cfg.spec.obs_dim(r) for r in cfg.spec.roles]
    obs = torch.randn(5, cfg.spec.n_agents, cfg.spec.max_obs_dim)
    for i, d in enumerate(agent.obs_dims):  # the env zero-pads each row past the role's obs_dim
        obs[:, i, d:] = 0
    batched = agent.act(obs)
    for i, a in enumerate(actors):
        torch.testing.assert_close(a(obs[:, i, :a.obs_dim]), batched[:, i], rtol=1e-5, atol=1e-6)
    # and back: stacking the exported actors gives the same policy
    pol = ActorsPolicy(actors, cfg.spec.max_obs_dim)
    np.testing.assert_allclose(pol.act(obs.numpy()), batched.numpy(), rtol=1e-5, atol=1e-6)


def test_batched_mlp_is_n_independent_mlps():
    g = torch.Generator().manual_seed(0)
    m = BatchedMLP(3, 4, (8, 8), 2, "tanh", g)
    x = torch.randn(3, 6, 4)
    y = m(x)
    for i in range(3):
        h = x[i]
        for k in range(3):
            h = h @ m.weights[k][i] + m.biases[k][i, 0]
            h = torch.relu(h) if k < 2 else torch.tanh(h)
        torch.testing.assert_close(h, y[i])


def test_replay_buffer_wraps_and_round_trips_newest_first_kept():
    buf = ReplayBuffer(5, 2, 3)
    for start in (0, 3, 6):  # 9 transitions into 5 slots
        obs = torch.arange(start, start + 3, dtype=torch.float32).view(3, 1, 1).expand(3, 2, 3)
        buf.add(obs, torch.zeros(3, 2, 2), torch.zeros(3, 2), obs + 0.5)
    assert len(buf) == 5
    assert sorted(buf.obs[:, 0, 0].tolist()) == [4, 5, 6, 7, 8]
    sd = buf.state_dict()
    assert sd["obs"][:, 0, 0].tolist() == [4, 5, 6, 7, 8]  # insertion order
    small = ReplayBuffer(3, 2, 3)
    small.load_state_dict(sd)
    assert sorted(small.obs[:, 0, 0].tolist()) == [6, 7, 8]  # a smaller buffer keeps the newest
    o, a, r, n, na = buf.sample(100, torch.Generator().manual_seed(0))
    assert o.shape == (100, 2, 3) and torch.equal(n, o + 0.5)
    assert na.shape == (100, 2, 2) and not na.any()  # no next actions given: zeros
    with pytest.raises(ValueError, match="empty"):
        ReplayBuffer(4, 1, 1).sample(1, torch.Generator())


def test_gradient_clipping_is_per_agent():
    p = torch.nn.Parameter(torch.zeros(2, 3))
    p.grad = torch.tensor([[3.0, 4.0, 0.0], [0.3, 0.4, 0.0]])  # norms 5 and 0.5
    norms = clip_grad_norm_per_agent([p], 1.0)
    torch.testing.assert_close(norms, torch.tensor([5.0, 0.5]), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(p.grad[0].norm(), torch.tensor(1.0), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(p.grad[1], torch.tensor([0.3, 0.4, 0.0]))  # under the cap: untouched


def _fill(agent: MADDPG, cfg: ExperimentConfig, n: int = 64) -> ReplayBuffer:
    sp = cfg.spec
    buf = ReplayBuffer(cfg.train.buffer_size, sp.n_agents, sp.max_obs_dim)
    g = torch.Generator().manual_seed(1)
    buf.add(torch.randn(n, sp.n_agents, sp.max_obs_dim, generator=g), torch.rand(n, sp.n_agents, 2, generator=g),
            torch.randn(n, sp.n_agents, generator=g), torch.randn(n, sp.n_agents, sp.max_obs_dim, generator=g))
    return buf


def test_update_trains_every_agent_and_static_evaders_stay_put():
    for evaders in ("learned", "static"):
        cfg = _cfg(evaders=evaders)
        agent = MADDPG(cfg.spec, cfg.train)
        before = [p.detach().clone() for p in agent.actors.parameters()]
        buf = _fill(agent, cfg)
        g = torch.Generator().manual_seed(2)
        for _ in range(3):
            losses = agent.update(buf.sample(cfg.train.batch_size, g))
        assert all(np.isfinite(v) for v in losses.values())
        assert agent.updates == 3
        changed = torch.stack([(p.detach() - b).reshape(p.shape[0], -1).abs().sum(1)
                               for p, b in zip(agent.actors.parameters(), before)]).sum(0)
        evader = cfg.spec.team.indices(Role.EVADER)[0]
        assert (changed[:evader] > 0).all()
        if evaders == "static":
            assert changed[evader] == 0
            assert (agent.act(torch.randn(4, cfg.spec.n_agents, cfg.spec.max_obs_dim), noise_std=0.5)[:, evader]
                    == 0).all()
        else:
            assert changed[evader] > 0


def test_state_dict_round_trip_gives_identical_updates():
    cfg = _cfg()
    a, b = MADDPG(cfg.spec, cfg.train), MADDPG(cfg.spec, dataclasses.replace(cfg.train, seed=99))
    buf = _fill(a, cfg)
    a.update(buf.sample(16, torch.Generator().manual_seed(0)))
    b.load_state_dict(a.state_dict())
    batch = buf.sample(16, torch.Generator().manual_seed(5))
    la, lb = a.update(batch), b.update(batch)
    assert la == lb
    for p, q in zip(a.actors.parameters(), b.actors.parameters()):
        assert torch.equal(p, q)


def test_train_config_errors_name_the_field():
    from runtime.spec import SpecError
    with pytest.raises(SpecError, match="train.batch_size"):
        TrainConfig(batch_size=10, buffer_size=5)
    with pytest.raises(SpecError, match="train.device"):
        TrainConfig(device="tpu")
    with pytest.raises(SpecError, match="train.noise_std"):
        TrainConfig(noise_std=-1.0)
    with pytest.raises(SpecError, match="train.int8_robustness"):
        TrainConfig(int8_robustness=-1.0)


def test_state_dict_round_trip_with_the_int8_penalty_gives_identical_updates():
    cfg = _cfg(int8_robustness=5.0)
    a, b = MADDPG(cfg.spec, cfg.train), MADDPG(cfg.spec, dataclasses.replace(cfg.train, seed=99))
    buf = _fill(a, cfg)
    a.update(buf.sample(16, torch.Generator().manual_seed(0)))
    b.load_state_dict(a.state_dict())  # includes the penalty's noise stream
    batch = buf.sample(16, torch.Generator().manual_seed(5))
    la, lb = a.update(batch), b.update(batch)
    assert la == lb and la["int8_sensitivity"] > 0
    assert "int8_sensitivity" not in MADDPG(cfg.spec, dataclasses.replace(cfg.train, int8_robustness=0.0)).update(
        batch)


def test_int8_sensitivity_is_the_action_change_under_one_int8_step_and_training_on_it_cuts_the_real_int8_error():
    """The penalty measures what int8 rounding does (uniform noise of one step per output neuron), and
    descending it makes the actors' real int8 rounding (``firmware_export.quantize``) move the actions less on
    observations uniform in the spec's ranges, while the actions stay close to where they started."""
    from firmware_export.quantize import round_nearest
    cfg = _cfg()
    agent = MADDPG(cfg.spec, cfg.train)
    with torch.no_grad():  # spread the weights like a trained actor's (a fresh one is insensitive)
        for w in agent.actors.weights:
            w.mul_(4.0)
    n, d = cfg.spec.n_agents, cfg.spec.max_obs_dim
    obs = agent._obs_lo + agent._obs_span * torch.rand(n, 2000, d, generator=torch.Generator().manual_seed(1))

    def int8_error() -> float:  # mean |action change| when the hidden layers are rounded to int8 (nearest)
        with torch.no_grad():
            ws = [w.detach() for w in agent.actors.weights]
            wq = []
            for li, w in enumerate(ws):
                if li == len(ws) - 1:
                    wq.append(w)
                    continue
                rows = []
                for i in range(n):  # the C's layout is [out, in]: round each agent's transposed weight
                    q, s = round_nearest(w[i].T.double().numpy())
                    rows.append(torch.tensor((q.astype(np.float64) * s[:, None].astype(np.float64)).T,
                                             dtype=torch.float32))
                wq.append(torch.stack(rows))
            x, xq = obs, obs
            for li, (w, q, b) in enumerate(zip(ws, wq, agent.actors.biases)):
                x, xq = x @ w + b, xq @ q + b
                if li < len(ws) - 1:
                    x, xq = torch.relu(x), torch.relu(xq)
            return float((torch.tanh(x) - torch.tanh(xq)).abs().mean())

    with torch.no_grad():
        start = agent.actors(obs).clone()
    s0, e0 = float(agent.int8_sensitivity(obs[:, :256]).mean()), int8_error()
    opt = torch.optim.Adam(agent.actors.parameters(), lr=3e-3)
    for _ in range(200):
        idx = torch.randint(0, 2000, (256,), generator=agent.reg_gen)
        batch = obs[:, idx]
        loss = 100.0 * agent.int8_sensitivity(batch).sum() + 20.0 * (agent.actors(batch) - start[:, idx]).pow(2).mean(
            (1, 2)).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    s1, e1 = float(agent.int8_sensitivity(obs[:, :256]).mean()), int8_error()
    with torch.no_grad():
        drift = float((agent.actors(obs) - start).abs().mean())
    # measured: penalty 0.0062 -> 0.0044, mean int8 error 0.0026 -> 0.0012, mean action drift 0.037
    assert s1 < 0.8 * s0 and e1 < 0.6 * e0, (s0, s1, e0, e1)
    assert drift < 0.1


def test_scripted_evaders_act_in_training_but_do_not_learn(tmp_path):
    from training.train import Trainer
    cfg = _cfg(evaders="scripted", steps=40, n_envs=2, warmup_steps=10, log_every=20, checkpoint_every=1000,
               buffer_size=200,
               checkpoint_buffer=False)
    tr = Trainer(cfg, tmp_path / "run")
    before = [p.detach().clone() for p in tr.agent.actors.parameters()]
    tr.run(progress=False)
    ev = cfg.spec.team.indices(Role.EVADER)[0]
    n = len(tr.buffer)
    assert n == 80 and tr.agent.updates > 0
    assert tr.buffer.act[:n, ev].abs().sum() > 0  # the fleeing evaders moved, and the critics saw it
    for p, b in zip(tr.agent.actors.parameters(), before):
        assert torch.equal(p[ev], b[ev])  # their actor did not train
        assert not torch.equal(p[0], b[0])


def test_replay_buffer_keeps_next_actions_and_loads_old_buffers_without_them(caplog):
    buf = ReplayBuffer(8, 2, 3)
    obs = torch.arange(4, dtype=torch.float32).view(4, 1, 1).expand(4, 2, 3)
    buf.add(obs, torch.zeros(4, 2, 2), torch.zeros(4, 2), obs + 0.5, obs[:, :, :2] + 0.25)
    o, _, _, _, na = buf.sample(50, torch.Generator().manual_seed(0))
    assert torch.equal(na, o[:, :, :2] + 0.25)
    sd = buf.state_dict()
    again = ReplayBuffer(8, 2, 3)
    again.load_state_dict(sd)
    assert torch.equal(again.next_act[:4], buf.next_act[:4])
    old = {k: v for k, v in sd.items() if k != "next_act"}  # a checkpoint from before next actions
    with caplog.at_level("WARNING", logger="training.maddpg"):
        again.load_state_dict(old)
    assert len(again) == 4 and not again.next_act.any()
    assert "zero next actions" in caplog.text


def test_td_target_uses_the_stored_next_action_of_scripted_agents_and_the_target_actor_of_learners():
    cfg = _cfg(evaders="scripted")
    agent = MADDPG(cfg.spec, cfg.train)
    sp = cfg.spec
    n, k, ev = sp.n_agents, 8, sp.team.indices(Role.EVADER)[0]
    g = torch.Generator().manual_seed(3)
    obs, next_obs = (torch.randn(k, n, sp.max_obs_dim, generator=g) for _ in range(2))
    rew = torch.randn(k, n, generator=g)
    stored = torch.rand(k, n, 2, generator=g) * 2 - 1  # what every agent "did" at next_obs
    batch = (obs, torch.zeros(k, n, 2), rew, next_obs, stored)
    y = agent.td_target(batch)
    # by hand: the learners' next actions from their target actors, the scripted evader's as stored
    expected_act = agent.actors_tgt(next_obs.transpose(0, 1)).transpose(0, 1).clone()
    expected_act[:, ev] = stored[:, ev]
    with torch.no_grad():
        q = agent.critics_tgt(next_obs.reshape(k, -1), expected_act.reshape(k, -1))
    torch.testing.assert_close(y, rew.t() * cfg.train.reward_scale + cfg.train.gamma * q)
    # the scripted evader's stored action moves every critic's target; a learner's stored action does not
    moved = stored.clone()
    moved[:, ev] = -stored[:, ev]
    assert (agent.td_target((*batch[:4], moved)) - y).abs().amax(1).min() > 0
    learner = stored.clone()
    learner[:, 0] = -stored[:, 0]
    assert torch.equal(agent.td_target((*batch[:4], learner)), y)
    # a learned evader uses its target actor whatever was stored
    co = MADDPG(sp, dataclasses.replace(cfg.train, evaders="learned"))
    assert torch.equal(co.td_target(batch), co.td_target((*batch[:4], moved)))
