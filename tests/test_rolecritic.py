"""``train.critic = "role"`` (training.rolecritic), the extra cloning steps, TD3+BC's decaying weight and the
avoidance layer between the actors and the world in training."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from runtime.avoidance import avoid_agents
from runtime.spec import SpecError
from training.config import ExperimentConfig, TrainConfig
from training.maddpg import MADDPG
from training.rolecritic import RoleCriticMADDPG, make_learner
from training.train import Trainer


def _cfg(spec: dict | None = None, **train) -> ExperimentConfig:
    return ExperimentConfig.from_dict({
        "name": "role_critic_check",
        "spec": spec or {"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 2}},
        "train": {"steps": 200, "n_envs": 8, "seed": 0, "batch_size": 64, "warmup_steps": 20, "threads": 1,
                  "log_every": 100, "checkpoint_every": 100000, "checkpoint_buffer": False, "critic": "role",
                  **train}})


def _batch(spec, k: int = 64, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    n, d = spec.n_agents, spec.max_obs_dim
    obs = torch.rand(k, n, d, generator=g) * 2 - 1
    nxt = torch.rand(k, n, d, generator=g) * 2 - 1
    act = torch.rand(k, n, 2, generator=g) * 2 - 1
    rew = torch.randn(k, n, generator=g)
    teach = torch.tanh(2 * obs[..., :2])
    return (obs, act, rew, nxt, torch.full((k, n, 2), float("nan")), teach)


def test_make_learner_picks_the_role_critic_and_bad_values_name_the_field():
    cfg = _cfg()
    assert isinstance(make_learner(cfg.spec, cfg.train), RoleCriticMADDPG)
    assert type(make_learner(cfg.spec, dataclasses.replace(cfg.train, critic="global"))) is MADDPG
    with pytest.raises(SpecError, match=r"train\.critic: 'roles' is not one of 'local', 'global', 'role'"):
        _cfg(critic="roles")
    for key, value in (("imitation_updates", -1), ("imitation_decay_steps", -5), ("imitation_batch", 0)):
        with pytest.raises(SpecError, match=rf"train\.{key}"):
            _cfg(teacher="classical", **{key: value})
    with pytest.raises(SpecError, match="train.teacher = 'classical'"):
        _cfg(imitation_updates=2)


@pytest.mark.parametrize("algorithm", ["maddpg", "matd3"])
def test_each_agent_reads_its_own_head_of_its_roles_critic(algorithm):
    cfg = _cfg(algorithm=algorithm)
    agent = RoleCriticMADDPG(cfg.spec, cfg.train)
    roles = list(cfg.spec.roles)
    with torch.no_grad():  # every critic outputs the constant 10 x model + head on its heads
        for w in agent.critics_tgt.mlp.weights:
            w.zero_()
        for b in agent.critics_tgt.mlp.biases:
            b.zero_()
        last = agent.critics_tgt.mlp.biases[-1]
        for m in range(last.shape[0]):
            last[m, 0] = 10.0 * m + torch.arange(last.shape[-1], dtype=torch.float32)
    batch = _batch(cfg.spec)
    y = agent.td_target(batch)  # [N, K]
    present = sorted(set(roles), key=roles.index)
    for i, r in enumerate(roles):
        head = roles[:i].count(r)
        want = 10.0 * present.index(r) + head  # twin 0's value (with twins both are >= it: the min is twin 0)
        expect = batch[2][:, i] * cfg.train.reward_scale + cfg.train.gamma * want
        torch.testing.assert_close(y[i], expect)


def test_an_actor_step_raises_every_learning_agents_own_value_under_a_fixed_critic():
    cfg = _cfg(actor_lr=1e-3)
    agent = RoleCriticMADDPG(cfg.spec, cfg.train)
    obs, act, *_ = _batch(cfg.spec, k=256)
    n = cfg.spec.n_agents

    def own_values() -> torch.Tensor:
        with torch.no_grad():
            mu = agent.actors(agent.actor_input(obs.transpose(0, 1)), agent._actor_ix)  # [N, K, 2]
            state = agent.critic_input(obs)
            out = []
            for i in range(n):  # agent i's head with its own action replaced by its actor's
                joint = act.clone()
                joint[:, i] = mu[i]
                q = agent._per_agent(agent.critics(torch.cat([state, joint.reshape(len(obs), -1)], 1)), 1)
                out.append(q[i].mean())
            return torch.stack(out)

    before = own_values()
    for _ in range(20):
        agent._role_actor_step(obs, act, agent.critic_input(obs), None, False, 0.0)
    after = own_values()
    assert (after > before).all(), (before, after)


def test_the_role_critic_fits_returns_and_its_state_round_trips():
    cfg = _cfg()
    agent = RoleCriticMADDPG(cfg.spec, cfg.train)
    batch = _batch(cfg.spec)
    first = agent.update(batch)["critic_loss"]
    for _ in range(200):
        last = agent.update(batch)["critic_loss"]
    assert last < 0.5 * first, (first, last)
    twin = RoleCriticMADDPG(cfg.spec, cfg.train)
    twin.load_state_dict(agent.state_dict())
    torch.testing.assert_close(twin.td_target(batch), agent.td_target(batch))
    local = MADDPG(cfg.spec, dataclasses.replace(cfg.train, critic="local"))
    with pytest.raises(ValueError, match="train.critic"):
        local.load_state_dict(agent.state_dict())


def test_clone_steps_bring_the_actors_to_the_teacher():
    cfg = _cfg(teacher="classical", imitation_steps=100)
    agent = make_learner(cfg.spec, cfg.train)
    obs, *_, teach = _batch(cfg.spec, k=512)
    first = agent.clone_step(obs, teach)
    for _ in range(300):
        last = agent.clone_step(obs, teach)
    assert last < 0.2 * first, (first, last)


def test_the_imitation_weight_decays_after_the_imitation_phase(tmp_path):
    cfg = _cfg(teacher="classical", imitation_steps=100, imitation_weight=2.0, imitation_decay_steps=50)
    trainer = Trainer(cfg, tmp_path / "run")
    got = []
    for step in (0, 99, 100, 125, 150, 199):
        trainer.env_step = step
        got.append(trainer.imitation_weight())
    assert got == [2.0, 2.0, 2.0, 1.0, 0.0, 0.0]
    flat = Trainer(_cfg(teacher="classical", imitation_steps=100, imitation_weight=2.0), tmp_path / "flat")
    flat.env_step = 190
    assert flat.imitation_weight() == 2.0


def test_training_flies_the_actors_through_the_avoidance_layer_and_scripted_evaders_as_they_are(tmp_path):
    spec = {"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 2}, "avoidance": {"enabled": True}}
    cfg = _cfg(spec, opponent_mix=1.0, opponent_scripted=1.0)
    trainer = Trainer(cfg, tmp_path / "run")
    obs = trainer.env.reset()
    trainer.mixer.reset(np.arange(cfg.train.n_envs))
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (cfg.train.n_envs, cfg.spec.n_agents, 2))
    out = trainer._executed(obs, actions)
    scripted = trainer.mixer.scripted_rows()
    assert scripted.any() and not scripted[:, :cfg.spec.team.n_team].any()
    np.testing.assert_array_equal(out[scripted], actions[scripted])
    layered = avoid_agents(cfg.spec, obs, actions.copy())
    np.testing.assert_array_equal(out[~scripted], layered[~scripted])
    off = Trainer(_cfg(), tmp_path / "off")
    assert off._executed(obs, actions) is actions


def test_a_short_role_critic_run_with_the_layer_and_cloning_trains_and_resumes(tmp_path):
    spec = {"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 1}, "avoidance": {"enabled": True}}
    cfg = _cfg(spec, teacher="classical", imitation_steps=60, imitation_updates=2, imitation_batch=128,
               imitation_weight=1.0, imitation_decay_steps=40, share_params=True, obs_scaling=True,
               checkpoint_every=100)
    first = Trainer(cfg, tmp_path / "run")
    result = first.run(progress=False)
    assert result.env_steps == 200 and result.updates > 0
    rows = (tmp_path / "run" / "metrics.csv").read_text().splitlines()
    last = dict(zip(rows[0].split(","), rows[-1].split(",")))
    assert np.isfinite(float(last["critic_loss"])) and np.isfinite(float(last["actor_loss"]))
    assert (tmp_path / "run" / "actors_imitation.pt").is_file()
    longer = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=250))
    again = Trainer(longer, tmp_path / "run", resume=True)
    assert again.env_step == 200 and isinstance(again.agent, RoleCriticMADDPG)
    assert again.run(progress=False).env_steps == 250


def test_a_loaded_learner_keeps_its_configs_learning_rates():
    cfg = _cfg()
    saved = make_learner(cfg.spec, cfg.train).state_dict()
    tuned = make_learner(cfg.spec, dataclasses.replace(cfg.train, actor_lr=3e-4, critic_lr=2e-4))
    tuned.load_state_dict(saved)  # a fine-tune (--init-from) under new rates
    assert {g["lr"] for g in tuned.actor_opt.param_groups} == {3e-4}
    assert {g["lr"] for g in tuned.critic_opt.param_groups} == {2e-4}


def test_an_actor_snapshot_is_evaluated_like_a_run(tmp_path):
    from training.learned_eval import load_learned
    cfg = _cfg(steps=40, warmup_steps=10, batch_size=32, checkpoint_every=20, snapshot_actors=True)
    Trainer(cfg, tmp_path / "run").run(progress=False)
    snaps = sorted((tmp_path / "run" / "snapshots").glob("actors_*.pt"))
    assert [p.name for p in snaps] == ["actors_000020.pt", "actors_000040.pt"]
    _, policy, source = load_learned(run=snaps[0])
    assert source == str(snaps[0])
    obs = np.zeros((2, cfg.spec.n_agents, cfg.spec.max_obs_dim))
    assert policy.act(obs).shape == (2, cfg.spec.n_agents, 2)


def test_es_needs_shared_actors_and_sane_settings():
    with pytest.raises(SpecError, match=r"train\.es_iterations: evolution strategies fly one actor per role"):
        _cfg(es_iterations=3)
    for key, value in (("es_population", 0), ("es_sigma", 0.0), ("es_learned_share", 1.5), ("es_lr", -1.0),
                       ("es_capture_weight", -0.1), ("es_rank", "median"), ("es_pool", ["hider"]),
                       ("es_pool", ["orbiter", "orbiter"])):
        with pytest.raises(SpecError, match=rf"train\.{key}"):
            _cfg(share_params=True, es_iterations=3, **{key: value})


def test_an_es_phase_after_the_steps_writes_its_actors_and_resumes(tmp_path):
    spec = {"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 1}, "avoidance": {"enabled": True}}
    cfg = _cfg(spec, steps=40, warmup_steps=10, batch_size=32, share_params=True, es_iterations=2,
               es_population=2, es_episodes=2, es_checkpoint_every=1, snapshot_actors=True)
    first = Trainer(cfg, tmp_path / "run")
    first.run(progress=False)
    rows = (tmp_path / "run" / "es.csv").read_text().splitlines()
    assert len(rows) == 3 and rows[0].startswith("iteration,")
    assert (tmp_path / "run" / "snapshots" / "actors_es0002.pt").is_file()
    from training.checkpoint import load_actors
    _, agents, doc = load_actors(tmp_path / "run")
    assert doc["meta"]["es_iterations"] == 2
    # the team moved, the evader is the learner's
    _, before, _ = load_actors(tmp_path / "run" / "snapshots" / "actors_000040.pt")
    moved = [not torch.equal(a.net[0].weight, b.net[0].weight) for (_, _, a), (_, _, b) in zip(agents, before)]
    assert moved == [True, True, True, False]
    longer = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, es_iterations=3))
    again = Trainer(longer, tmp_path / "run", resume=True)
    again.run(progress=False)
    assert len((tmp_path / "run" / "es.csv").read_text().splitlines()) == 4


def test_the_es_fitness_is_the_weighted_sum_of_the_episode_metrics_captures_included():
    from runtime.metrics import EpisodeRecord
    from training.es import TeamES
    cfg = _cfg(share_params=True, es_iterations=1, es_tracking_weight=1.0, es_distance_weight=3.0,
               es_coverage_weight=0.1, es_contact_weight=0.2, es_capture_weight=0.05)
    es = TeamES.__new__(TeamES)  # fitness reads only the config
    es.tc = cfg.train
    recs = [EpisodeRecord(min_dist=0.3, avg_dist=1.0, max_dist=2.0, tracking_rate=0.7, coverage=0.8,
                          coverage_instant=0.2, collisions=3, captures=6, steps=100, teammate=1, team_obstacle=1,
                          evader=1),
            EpisodeRecord(min_dist=0.5, avg_dist=1.0, max_dist=2.0, tracking_rate=0.4, coverage=0.6,
                          coverage_instant=0.2, collisions=0, captures=0, steps=100)]
    one = 0.7 - 3.0 * 0.3 + 0.1 * 0.8 - 0.2 * 2 + 0.05 * 6
    two = 0.4 - 3.0 * 0.5 + 0.1 * 0.6
    assert es.fitness(recs) == pytest.approx((one + two) / 2)
    no_captures = dataclasses.replace(cfg.train, es_capture_weight=0.0)
    es.tc = no_captures
    assert es.fitness(recs) == pytest.approx((one - 0.05 * 6 + two) / 2)
    es.tc = cfg.train  # each role's part (train.es_role_fitness): the pursuers' without coverage, the scouts' coverage
    from runtime.spec import Role
    np.testing.assert_allclose(es.episode_fitness(recs, Role.PURSUER), [one - 0.1 * 0.8, two - 0.1 * 0.6])
    np.testing.assert_allclose(es.episode_fitness(recs, Role.SCOUT), [0.1 * 0.8 - 0.2 * 2, 0.1 * 0.6])


def _rec(min_dist: float):
    from runtime.metrics import EpisodeRecord
    return EpisodeRecord(min_dist=min_dist, avg_dist=1.0, max_dist=2.0, tracking_rate=0.5, coverage=0.5,
                         coverage_instant=0.1, collisions=0, captures=0, steps=100)


def test_es_rank_episode_gives_every_episode_the_same_say():
    """Member a is a little better than b in two episodes and much worse in a third: by total fitness b wins,
    by per-episode ranks a wins (2 of 3 episodes)."""
    from training.es import TeamES
    es = TeamES.__new__(TeamES)
    a = [_rec(0.20), _rec(0.20), _rec(1.50)]
    b = [_rec(0.21), _rec(0.21), _rec(0.50)]
    c = [_rec(0.30), _rec(0.30), _rec(2.00)]
    es.tc = _cfg(share_params=True, es_iterations=1).train
    total, _ = es.ranking_scores([a, b, c])
    assert total[1] > total[0] > total[2]
    es.tc = _cfg(share_params=True, es_iterations=1, es_rank="episode").train
    by_episode, _ = es.ranking_scores([a, b, c])
    np.testing.assert_allclose(by_episode, [(2 + 2 + 1) / 3, (1 + 1 + 2) / 3, 0.0])


def test_es_pool_limits_the_scripted_opponents_es_meets(monkeypatch):
    """With ``train.es_pool`` the ES rollouts' training pool holds only those behaviours."""
    from training import es as es_mod
    made = []
    real = es_mod.TrainingPool

    def spy(*args, **kw):
        pool = real(*args, **kw)
        made.append(list(pool.kinds))
        return pool

    monkeypatch.setattr(es_mod, "TrainingPool", spy)
    spec = {"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 1}, "avoidance": {"enabled": True}}
    for pool, want in ((["orbiter", "billiard"], ["orbiter", "billiard"]), ([], sorted(es_mod.TrainingPool().kinds))):
        cfg = _cfg(spec, share_params=True, es_iterations=1, es_population=1, es_episodes=2, es_learned_share=0.0,
                   es_pool=pool)
        from training.maddpg import MADDPG
        learner = MADDPG(cfg.spec, cfg.train)
        team = es_mod.TeamES(cfg.spec, cfg.rewards, learner.to_actors(), cfg.train, seed=0)
        made.clear()
        row = team.step()
        assert np.isfinite(row["fitness"]) and sorted(made[-1]) == sorted(want)


def test_es_role_fitness_moves_each_role_by_its_own_terms_only(monkeypatch):
    """Rollouts faked so that the pursuers' weights set the distance and the scouts' the coverage: with
    ``es_role_fitness`` the pursuers' step does not depend on the coverage the members reached, nor the scouts'
    on the distance; with the team's one fitness, it does."""
    from runtime.metrics import EpisodeRecord
    from training.es import TeamES
    spec = {"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 1}}
    rng = np.random.default_rng(3)

    def step(role_fitness: str, cover_sign: float, dist_sign: float) -> tuple[np.ndarray, np.ndarray]:
        cfg = _cfg(spec, share_params=True, es_iterations=1, es_population=6, es_episodes=1,
                   es_coverage_weight=1.0, es_role_fitness=role_fitness)
        team = TeamES(cfg.spec, cfg.rewards, MADDPG(cfg.spec, cfg.train).to_actors(), cfg.train, seed=0)
        sp = team.sizes[0]
        if not dirs:  # the directions that pay, drawn once for every call
            dirs.update(p=rng.standard_normal(sp), s=rng.standard_normal(team.sizes[1]))
        dp, ds = dirs["p"], dirs["s"]

        def fake(thetas, episodes, seed):
            d = thetas - team.theta
            return [[EpisodeRecord(min_dist=0.5 + dist_sign * 1e3 * (x[:sp] @ dp), avg_dist=1.0, max_dist=2.0,
                                   tracking_rate=0.5, coverage=0.5 + cover_sign * 1e3 * (x[sp:] @ ds),
                                   coverage_instant=0.1, collisions=0, captures=0, steps=100)] for x in d]

        monkeypatch.setattr(team, "rollout", fake)
        before = team.theta.copy()
        team.step()
        return (team.theta - before)[:sp], (team.theta - before)[sp:]

    dirs: dict[str, np.ndarray] = {}
    p1, s1 = step("split", 1.0, 1.0)
    p2, s2 = step("split", -1.0, 1.0)  # only the coverage turned around: the pursuers' step stays
    p3, s3 = step("split", 1.0, -1.0)  # only the distance turned around: the scouts' step stays
    np.testing.assert_array_equal(p1, p2)
    np.testing.assert_array_equal(s1, s3)
    assert not np.array_equal(s1, s2) and not np.array_equal(p1, p3)
    q1, r1 = step("pursuers", 1.0, 1.0)
    q2, _ = step("pursuers", -1.0, 1.0)  # the pursuers' step ignores the coverage, the scouts' the team's
    _, r3 = step("pursuers", 1.0, -1.0)
    np.testing.assert_array_equal(q1, q2)
    np.testing.assert_array_equal(q1, p1)
    assert not np.array_equal(r1, r3)
    t1, _ = step("team", 1.0, 1.0)
    t2, _ = step("team", -1.0, 1.0)  # the team's one fitness: the coverage moves the pursuers too
    assert not np.array_equal(t1, t2)
    for bad in ({"es_role_fitness": "split", "es_coverage_weight": 0.0}, {"es_role_fitness": "roles"}):
        with pytest.raises(SpecError, match=r"train\.es_role_fitness"):
            _cfg(spec, share_params=True, es_iterations=1, **bad)


def test_es_pursuer_iterations_freezes_the_pursuers_after_k_iterations(monkeypatch):
    """``train.es_pursuer_iterations = k``: the pursuers' weights move in ES's first k iterations only; after them
    every member flies the pursuers' centre and only the scouts' weights step. The first k iterations are those of
    a run without the option, to the bit. Off by default; a k outside [0, es_iterations] names the field."""
    from runtime.metrics import EpisodeRecord
    from training.es import TeamES
    spec = {"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 1}}
    assert TrainConfig().es_pursuer_iterations is None

    def run(k):
        cfg = _cfg(spec, share_params=True, es_iterations=3, es_population=4, es_episodes=1,
                   es_coverage_weight=1.0, es_role_fitness="pursuers", es_pursuer_iterations=k)
        team = TeamES(cfg.spec, cfg.rewards, MADDPG(cfg.spec, cfg.train).to_actors(), cfg.train, seed=0)
        sp = team.sizes[0]
        flown = []
        w = np.random.default_rng(5).standard_normal(team.theta.size)

        def fake(thetas, episodes, seed):
            flown.append(thetas.copy())
            return [[EpisodeRecord(min_dist=0.5 - 1e3 * (x - team.theta) @ w, avg_dist=1.0, max_dist=2.0,
                                   tracking_rate=0.5, coverage=0.5 + 1e3 * (x - team.theta) @ w,
                                   coverage_instant=0.1, collisions=0, captures=0, steps=100)] for x in thetas]

        monkeypatch.setattr(team, "rollout", fake)
        thetas = [team.theta.copy()]
        for _ in range(3):
            team.step()
            thetas.append(team.theta.copy())
        return sp, thetas, flown

    sp, free, _ = run(None)
    _, froz, flown = run(1)
    np.testing.assert_array_equal(free[1], froz[1])  # the first iteration: as without the option
    assert np.abs(froz[1][:sp] - froz[0][:sp]).max() > 0
    for i in (2, 3):  # then the pursuers stand still, every member flies their centre, the scouts move on
        np.testing.assert_array_equal(froz[i][:sp], froz[1][:sp])
        assert np.abs(froz[i][sp:] - froz[i - 1][sp:]).max() > 0
        members = flown[i - 1][:, :sp]
        np.testing.assert_array_equal(members, np.broadcast_to(froz[i - 1][:sp], members.shape))
    assert np.abs(free[3][:sp] - free[1][:sp]).max() > 0  # without it they go on
    for bad in (-1, 4):
        with pytest.raises(SpecError, match=r"train\.es_pursuer_iterations"):
            _cfg(spec, share_params=True, es_iterations=3, es_pursuer_iterations=bad)
