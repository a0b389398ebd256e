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
    o, a, r, n, na, te = buf.sample(100, torch.Generator().manual_seed(0))
    assert o.shape == (100, 2, 3) and torch.equal(n, o + 0.5)
    assert na.shape == (100, 2, 2) and torch.isnan(na).all()  # none given: NaN, the target actors decide
    assert te.shape == (100, 2, 2) and torch.isnan(te).all()  # no teacher
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
    o, _, _, _, na, _ = buf.sample(50, torch.Generator().manual_seed(0))
    assert torch.equal(na, o[:, :, :2] + 0.25)
    sd = buf.state_dict()
    again = ReplayBuffer(8, 2, 3)
    again.load_state_dict(sd)
    assert torch.equal(again.next_act[:4], buf.next_act[:4])
    old = {k: v for k, v in sd.items() if k != "next_act"}  # a checkpoint from before next actions
    with caplog.at_level("WARNING", logger="training.maddpg"):
        again.load_state_dict(old)
    assert len(again) == 4 and torch.isnan(again.next_act[:4]).all()  # unknown: the target actors decide
    assert "without next actions" in caplog.text
    assert torch.isnan(again.teach[:4]).all()  # a buffer from before teachers: no teacher actions


def test_td_target_uses_the_stored_next_action_of_scripted_agents_and_the_target_actor_of_learners():
    cfg = _cfg(evaders="scripted")
    agent = MADDPG(cfg.spec, cfg.train)
    sp = cfg.spec
    n, k, ev = sp.n_agents, 8, sp.team.indices(Role.EVADER)[0]
    g = torch.Generator().manual_seed(3)
    obs, next_obs = (torch.randn(k, n, sp.max_obs_dim, generator=g) for _ in range(2))
    rew = torch.randn(k, n, generator=g)
    stored = torch.rand(k, n, 2, generator=g) * 2 - 1  # what every agent "did" at next_obs
    stored[:, agent._learns] = float("nan")  # as the trainer stores it: the learners' target actors decide
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
    # a learned evader uses its target actor where nothing is given (NaN), and a given action where it was
    # frozen or scripted in that env (opponent mixing)
    co = MADDPG(sp, dataclasses.replace(cfg.train, evaders="learned"))
    unknown = torch.full_like(stored, float("nan"))
    assert torch.equal(co.td_target((*batch[:4], unknown)), co.td_target(batch[:4]))
    assert (co.td_target(batch) - co.td_target((*batch[:4], moved))).abs().amax(1).min() > 0


# -- learner options (issue 13): each off by default -----------------------------------------------------

OPTION_SETS = {
    "default": {},
    "share": {"share_params": True},
    "global": {"critic": "global"},
    "matd3": {"algorithm": "matd3"},
    "scaling": {"obs_scaling": True},
    "all": {"share_params": True, "critic": "global", "algorithm": "matd3", "obs_scaling": True,
            "int8_robustness": 1.0},
}


def _batch(cfg: ExperimentConfig, k: int = 16, seed: int = 1) -> tuple[torch.Tensor, ...]:
    sp = cfg.spec
    n, d = sp.n_agents, sp.max_obs_dim
    g = torch.Generator().manual_seed(seed)
    obs, next_obs = (torch.randn(k, n, d, generator=g) for _ in range(2))
    for i, dim in enumerate(sp.obs_dim(r) for r in sp.roles):  # zero padding, as the env gives
        obs[:, i, dim:] = 0
        next_obs[:, i, dim:] = 0
    return (obs, torch.rand(k, n, 2, generator=g) * 2 - 1, torch.randn(k, n, generator=g), next_obs,
            torch.rand(k, n, 2, generator=g) * 2 - 1)


def test_options_are_off_by_default_and_on_in_the_shipped_configs():
    """The defaults are the paper's MADDPG; the shipped recipe (issue 13) turns on role critics, one actor per
    role and observation scaling, while the paper's configs keep the defaults."""
    from pathlib import Path
    tc = TrainConfig()
    assert (tc.algorithm, tc.critic, tc.share_params, tc.obs_scaling) == ("maddpg", "local", False, False)
    root = Path(__file__).resolve().parent.parent
    for name, want in (("role_based", ("maddpg", "role", True, True)), ("multi_target", ("maddpg", "role", True, True)),
                       ("paper_role_based", ("maddpg", "local", False, False)),
                       ("paper_multi_target", ("maddpg", "local", False, False))):
        shipped = ExperimentConfig.from_toml(root / "configs" / f"{name}.toml").train
        assert (shipped.algorithm, shipped.critic, shipped.share_params, shipped.obs_scaling) == want, name


def test_option_errors_name_the_field():
    from runtime.spec import SpecError
    for bad, field in (({"algorithm": "td3"}, "train.algorithm"), ({"critic": "joint"}, "train.critic"),
                       ({"policy_delay": 0}, "train.policy_delay"), ({"target_noise": -0.1}, "train.target_noise"),
                       ({"target_noise_clip": -1.0}, "train.target_noise_clip"),
                       ({"share_params": 1}, "train.share_params"), ({"obs_scaling": "yes"}, "train.obs_scaling")):
        with pytest.raises(SpecError, match=field):
            TrainConfig(**bad)
    cfg = ExperimentConfig.from_dict({"spec": {"sensing": {"n_obstacles_observed": 1}}, "train": {"critic": "global"}})
    with pytest.raises(SpecError, match="sensing.n_obstacles_observed"):
        MADDPG(cfg.spec, cfg.train)


@pytest.mark.parametrize("name", sorted(OPTION_SETS))
def test_every_option_trains_round_trips_and_exports_one_actor_per_agent(name, tmp_path):
    from training.checkpoint import load_actors, save_actors
    cfg = _cfg(**OPTION_SETS[name])
    a, b = MADDPG(cfg.spec, cfg.train), MADDPG(cfg.spec, dataclasses.replace(cfg.train, seed=99))
    before = [p.detach().clone() for p in a.actors.parameters()]
    for s in range(4):
        losses = a.update(_batch(cfg, seed=s))
    assert all(np.isfinite(v) for v in losses.values()) and "actor_loss" in losses
    assert any(not torch.equal(p, q) for p, q in zip(a.actors.parameters(), before))
    b.load_state_dict(a.state_dict())  # networks, optimizers, the random streams, matd3's delay phase
    for s in (5, 6, 7):  # three updates cover matd3's delayed actor step and its smoothing noise
        batch = _batch(cfg, seed=s)
        assert a.update(batch) == b.update(batch)
    for p, q in zip(list(a.actors.parameters()) + list(a.critics_tgt.parameters()),
                    list(b.actors.parameters()) + list(b.critics_tgt.parameters())):
        assert torch.equal(p, q)
    # the export contract: one actor per agent taking the role's raw observation, acting as the learner does
    obs = _batch(cfg, k=32, seed=9)[0]
    path = save_actors(tmp_path / "actors.pt", cfg.spec, a.to_actors())
    _, loaded, _ = load_actors(path)
    assert [act.obs_dim for _, _, act in loaded] == [cfg.spec.obs_dim(r) for r in cfg.spec.roles]
    want = a.act(obs)
    with torch.no_grad():  # the opponent snapshots' form: one row per agent on raw observations
        torch.testing.assert_close(a.frozen_actors()(obs.transpose(0, 1)).transpose(0, 1), want, rtol=1e-5, atol=2e-6)
    for i, (_, _, actor) in enumerate(loaded):
        with torch.no_grad():
            torch.testing.assert_close(actor(obs[:, i, :actor.obs_dim]), want[:, i], rtol=1e-5, atol=2e-6)


def test_a_learner_state_loads_only_into_the_same_options():
    cfg = _cfg(critic="global")
    sd = MADDPG(cfg.spec, cfg.train).state_dict()
    with pytest.raises(ValueError, match="train.critic = 'global'"):
        MADDPG(cfg.spec, dataclasses.replace(cfg.train, critic="local")).load_state_dict(sd)
    old = MADDPG(cfg.spec, TrainConfig()).state_dict()  # a state written before the options existed
    del old["options"], old["target_gen"], old["last_actor"]
    MADDPG(cfg.spec, TrainConfig()).load_state_dict(old)
    with pytest.raises(ValueError, match="train.share_params = False"):
        MADDPG(cfg.spec, TrainConfig(share_params=True)).load_state_dict(old)


def test_shared_parameters_one_actor_and_critic_per_role_that_tells_its_agents_apart():
    cfg = _cfg(share_params=True)
    sp = cfg.spec  # 2 pursuers, 1 scout, 1 evader: 3 roles
    agent = MADDPG(sp, cfg.train)
    assert agent.actors.weights[0].shape[0] == 3 and agent.critics.w_obs.shape[0] == 3
    p0, p1 = sp.team.indices(Role.PURSUER)
    obs = _batch(cfg)[0]
    obs[:, p1] = obs[:, p0]
    a = agent.act(obs)
    assert torch.equal(a[:, p0], a[:, p1])  # one pursuer actor
    actors = agent.to_actors()
    assert len(actors) == sp.n_agents
    assert all(torch.equal(x, y) for x, y in zip(actors[p0].state_dict().values(), actors[p1].state_dict().values()))
    # the role's critic gets a one-hot of the agent it evaluates: same state and actions, different values
    state, act = agent.critic_input(obs), _batch(cfg)[1]
    q = agent.critics(state, act.reshape(act.shape[0], -1), index=agent._critic_ix, slot=agent._slot)
    assert q.shape == (sp.n_agents, obs.shape[0]) and not torch.equal(q[p0], q[p1])
    # one Adam step on the mean of the role's agents' losses: both pursuers' transitions move the model
    before = agent.actors.weights[0][0].detach().clone()
    agent.update(_batch(cfg))
    assert not torch.equal(agent.actors.weights[0][0], before)


def test_global_state_is_every_position_velocity_and_obstacle_of_the_world():
    from training.env import PursuitEnv
    from training.maddpg import global_state, global_state_dim
    cfg = ExperimentConfig.from_dict({"spec": {"team": {"n_pursuers": 2, "n_scouts": 2, "n_evaders": 2}}})
    sp = cfg.spec
    env = PursuitEnv(sp, n_envs=3, seed=4)
    obs = env.reset()
    rng = np.random.default_rng(0)
    for _ in range(5):
        obs, _, _, _ = env.step(rng.uniform(-1, 1, (3, sp.n_agents, 2)))
    s = env.state
    order = np.argsort(s.obstacle_pos[..., 0], axis=1)
    obst = np.concatenate([np.take_along_axis(s.obstacle_pos, order[..., None], 1),
                           np.take_along_axis(s.obstacle_radius, order, 1)[..., None]], -1)
    want = np.concatenate([s.pos.reshape(3, -1), s.vel.reshape(3, -1), obst.reshape(3, -1)], 1)
    got = global_state(sp, torch.as_tensor(obs, dtype=torch.float32))
    assert got.shape == (3, global_state_dim(sp)) == (3, 4 * sp.n_agents + 3 * sp.arena.n_obstacles)
    np.testing.assert_allclose(got.numpy(), want, atol=1e-5)


def test_matd3_takes_the_smaller_twin_with_clipped_smoothing_noise_and_delays_the_actor():
    cfg = _cfg(algorithm="matd3", evaders="scripted", policy_delay=2, target_noise=0.0)
    agent = MADDPG(cfg.spec, cfg.train)
    n = cfg.spec.n_agents
    assert agent.critics.w_obs.shape[0] == 2 * n  # twin critics
    obs, act, rew, next_obs, stored = _batch(cfg)
    ev = cfg.spec.team.indices(Role.EVADER)[0]
    stored[:, :ev] = float("nan")  # known: the scripted evader's next action only
    batch = (obs, act, rew, next_obs, stored)
    k = obs.shape[0]
    with torch.no_grad():
        na = agent.target_next_actions(next_obs, stored)
        q2 = agent.critics_tgt(next_obs.reshape(k, -1), na.reshape(k, -1)).view(2, n, k)
    assert (q2[0] != q2[1]).any()
    torch.testing.assert_close(agent.td_target(batch), rew.t() * 0.1 + 0.95 * torch.minimum(q2[0], q2[1]))
    # smoothing noise: clipped to +-target_noise_clip around the target actors, none on the scripted evader
    noisy = MADDPG(cfg.spec, dataclasses.replace(cfg.train, target_noise=10.0, target_noise_clip=0.1))
    clean = noisy.actors_tgt(next_obs.transpose(0, 1)).transpose(0, 1).detach()
    got = noisy.target_next_actions(next_obs, stored)
    diff = (got - clean)[:, :ev]
    assert diff.abs().max() <= 0.1 + 1e-6 and (diff.abs() > 0.09).float().mean() > 0.5
    assert torch.equal(got[:, ev], stored[:, ev])
    # delayed: the actors and every target move only on every 2nd update; the critics on every update
    snap = lambda m: [p.detach().clone() for p in m.parameters()]  # noqa: E731
    actors, targets, critics = snap(agent.actors), snap(agent.critics_tgt), snap(agent.critics)
    agent.update(batch)
    assert all(torch.equal(p, q) for p, q in zip(agent.actors.parameters(), actors))
    assert all(torch.equal(p, q) for p, q in zip(agent.critics_tgt.parameters(), targets))
    assert not torch.equal(agent.critics.w_obs, critics[0])
    agent.update(batch)
    assert not torch.equal(agent.actors.weights[0], actors[0])
    assert not torch.equal(agent.critics_tgt.w_obs, targets[0])


def test_obs_scaling_maps_the_spec_ranges_to_unit_and_folds_into_the_exported_first_layer():
    cfg = _cfg(obs_scaling=True)
    sp = cfg.spec
    agent = MADDPG(sp, cfg.train)
    n, d = sp.n_agents, sp.max_obs_dim
    lo, hi = agent._obs_lo, agent._obs_lo + agent._obs_span
    ends = agent.actor_input(torch.cat([lo, hi], dim=1))  # [N, 2, D]
    for i, dim in enumerate(agent.obs_dims):
        torch.testing.assert_close(ends[i, 0, :dim], -torch.ones(dim))
        torch.testing.assert_close(ends[i, 1, :dim], torch.ones(dim))
        assert not ends[i, :, dim:].any()  # padding stays zero
    with torch.no_grad():  # weights like a trained actor's, so that the fold is checked on real magnitudes
        for w in agent.actors.weights:
            w.mul_(3.0)
    g = torch.Generator().manual_seed(0)
    obs = (lo + agent._obs_span * (torch.rand(n, 500, d, generator=g) * 1.4 - 0.2)).transpose(0, 1)  # in and out
    want = agent.act(obs)
    with torch.no_grad():
        raw = agent.actors(obs.transpose(0, 1)).transpose(0, 1)
    assert (raw - want).abs().max() > 0.05  # the scaling matters
    for i, actor in enumerate(agent.to_actors()):
        with torch.no_grad():
            torch.testing.assert_close(actor(obs[:, i, :actor.obs_dim]), want[:, i], rtol=1e-5, atol=1e-5)


def test_the_offset_gain_scales_only_the_offset_columns_and_folds_into_the_exported_first_layer():
    from runtime.spec import SpecError
    plain, boosted = MADDPG(_cfg(obs_scaling=True).spec, _cfg(obs_scaling=True).train), None
    cfg = _cfg(obs_scaling=True, obs_offset_gain=4.0)
    boosted = MADDPG(cfg.spec, cfg.train)
    sp = cfg.spec
    for i, role in enumerate(sp.roles):
        cols = [c for f in sp.layout(role).fields for _ in range(f.rows) for c in f.columns]
        ratio = boosted._in_scale[i, 0, :len(cols)] / plain._in_scale[i, 0, :len(cols)]
        want = torch.tensor([4.0 if c in ("dx", "dy") else 1.0 for c in cols])
        torch.testing.assert_close(ratio, want)
        assert sum(c in ("dx", "dy") for c in cols) >= 2  # the targets' offsets at least
    with torch.no_grad():
        for w in boosted.actors.weights:
            w.mul_(3.0)
    g = torch.Generator().manual_seed(1)
    n, d = sp.n_agents, sp.max_obs_dim
    obs = (boosted._obs_lo + boosted._obs_span * torch.rand(n, 300, d, generator=g)).transpose(0, 1)
    want = boosted.act(obs)
    for i, actor in enumerate(boosted.to_actors()):
        with torch.no_grad():
            torch.testing.assert_close(actor(obs[:, i, :actor.obs_dim]), want[:, i], rtol=1e-5, atol=1e-5)
    for bad, field in (({"obs_offset_gain": 0.0, "obs_scaling": True}, "train.obs_offset_gain"),
                       ({"obs_offset_gain": float("inf"), "obs_scaling": True}, "train.obs_offset_gain"),
                       ({"obs_offset_gain": 2.0}, "train.obs_scaling = true")):
        with pytest.raises(SpecError, match=field):
            TrainConfig(**bad)
    # a learner state saved before the option existed loads with the default
    sd = plain.state_dict()
    del sd["options"]["obs_offset_gain"]
    MADDPG(plain.spec, plain.cfg).load_state_dict(sd)
    with pytest.raises(ValueError, match="train.obs_offset_gain = 1.0"):
        MADDPG(sp, cfg.train).load_state_dict(sd)


def test_obs_scaled_actors_export_to_onnx_that_acts_as_the_learner(tmp_path):
    from firmware_export.onnx_export import export_run
    from training.checkpoint import save_actors
    from training.maddpg import OnnxActorsPolicy
    cfg = _cfg(obs_scaling=True, share_params=True)
    agent = MADDPG(cfg.spec, cfg.train)
    agent.update(_batch(cfg))
    save_actors(tmp_path / "run" / "actors.pt", cfg.spec, agent.to_actors())
    export_run(tmp_path / "run", tmp_path / "models", n_random=200, n_recorded=50)
    obs = _batch(cfg, k=64, seed=3)[0]
    np.testing.assert_allclose(OnnxActorsPolicy(str(tmp_path / "models")).act(obs.numpy()), agent.act(obs).numpy(),
                               atol=1e-5)


def test_the_trainer_runs_every_option_with_opponent_snapshots_and_resumes(tmp_path):
    from training.train import Trainer
    cfg = _cfg(share_params=True, critic="global", algorithm="matd3", obs_scaling=True, opponent_mix=0.5,
               opponent_snapshot_every=10, steps=30, n_envs=2, warmup_steps=10, log_every=10, checkpoint_every=1000,
               buffer_size=200)
    tr = Trainer(cfg, tmp_path / "run")
    tr.run(progress=False)
    assert tr.agent.updates > 0 and tr.mixer.snapshots
    obs = _batch(cfg, k=8)[0]
    with torch.no_grad():  # a snapshot acts as the learner's exported actors did when it was taken
        assert tr.mixer.snapshots[-1](obs.transpose(0, 1)).shape == (cfg.spec.n_agents, 8, 2)
    longer = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=40))
    again = Trainer(longer, tmp_path / "run", resume=True)
    assert again.agent.updates == tr.agent.updates and len(again.mixer.snapshots) == len(tr.mixer.snapshots)
    again.run(progress=False)
    assert again.agent.updates > tr.agent.updates
