"""The held-out evader suite and the training pool: protocol, per-env parameters, disjointness, behaviours."""
import numpy as np
import pytest

from runtime.spec import SwarmSpec
from training.baselines import ClassicalPursuers, FleeingEvaders, RandomPolicy, TeamPolicy
from training.env import PursuitEnv
from training.evader_suite import (POOL, SUITE, ScriptedEvaders, TrainingPool, make_suite_evader, parse_suite)

SPEC = SwarmSpec.from_dict({"team": {"n_pursuers": 3, "n_scouts": 1, "n_evaders": 2},
                            "timing": {"episode_steps": 40}})
NT = SPEC.team.n_team


def _env(b=4, seed=0, spec=SPEC):
    env = PursuitEnv(spec, n_envs=b, seed=seed)
    return env, env.reset()


@pytest.mark.parametrize("kind", [*SUITE, *POOL])
def test_every_behaviour_follows_the_protocol_and_moves(kind):
    env, obs = _env()
    ev = (SUITE | POOL)[kind](seed=1)
    moved = 0.0
    for _ in range(60):  # through one automatic reset (episode_steps = 40)
        a = ev.act(obs, env)
        assert a.shape == (4, SPEC.n_agents, 2) and np.isfinite(a).all()
        assert (a[:, :NT] == 0).all() and (np.linalg.norm(a[:, NT:], axis=-1) <= 1 + 1e-9).all()
        moved += np.linalg.norm(a[:, NT:], axis=-1).mean()
        both = ClassicalPursuers().act(obs, env)
        both[:, NT:] = a[:, NT:]
        obs, *_ = env.step(both)
    assert moved / 60 > 0.1


def test_suite_and_pool_share_no_behaviour():
    suite, pool = set(SUITE.values()), set(POOL.values())
    assert len(suite) >= 4 and len(pool) >= 3
    assert not suite & pool and not set(SUITE) & set(POOL)
    for a in suite:  # not even through inheritance: every class derives from the base only
        for b in pool:
            assert not issubclass(a, b) and not issubclass(b, a)
    assert FleeingEvaders not in suite | pool  # the "scripted" evaluation evaders are in neither
    assert all(c.__bases__ == (ScriptedEvaders,) for c in suite | pool)


def test_parameters_differ_per_env_redraw_per_episode_and_follow_the_seed():
    env, obs = _env(b=6)
    ev = make_suite_evader("juker", seed=5)
    ev.act(obs, env)
    first = ev.p["period"].copy()
    assert len(np.unique(first)) == first.size  # every env and evader its own draw
    for _ in range(SPEC.timing.episode_steps):  # act at every step, as the evaluator and the trainer do
        obs, *_ = env.step(ev.act(obs, env))
    ev.act(obs, env)  # the envs were reset: step 0 again
    assert not np.isin(ev.p["period"], first).any()
    # the same seed draws the same parameters whatever the pursuers did in between
    runs = []
    for team in (ClassicalPursuers(), RandomPolicy(3)):
        env, obs = _env(b=6)
        e = make_suite_evader("juker", seed=5)
        pol = TeamPolicy(team, e)
        for _ in range(SPEC.timing.episode_steps + 1):
            obs, *_ = env.step(pol.act(obs, env))
        runs.append(e.p["period"].copy())
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], first)
    assert not np.array_equal(make_suite_evader("juker", 6).act(obs, env), make_suite_evader("juker", 5).act(obs, env))


def test_parse_suite():
    assert parse_suite("suite") == list(SUITE)
    assert parse_suite("suite:hider, wanderer") == ["hider", "wanderer"]
    with pytest.raises(ValueError, match="unknown suite kind nope"):
        parse_suite("suite:nope")
    with pytest.raises(ValueError, match="unknown suite evader"):
        make_suite_evader("orbiter")  # a pool behaviour is not in the suite


def _place(env, team_pos, evader_pos, obstacles=((0.0, 0.0, 0.4),), step=5):
    s = env.state
    s.pos[:, :NT] = team_pos
    s.pos[:, NT:] = evader_pos
    s.vel[:] = 0
    s.obstacle_pos[:] = np.array([o[:2] for o in obstacles])[None]
    s.obstacle_radius[:] = np.array([o[2] for o in obstacles])[None]
    s.step[:] = step


FAR_TEAM = [[-2.5, -2.5], [-2.5, -2.0], [-2.0, -2.5], [2.5, -2.5]]


def test_wanderer_ignores_the_pursuers():
    env, obs = _env(b=1)
    ev = make_suite_evader("wanderer", 0)
    ev.act(obs, env)  # draws the parameters at step 0
    _place(env, FAR_TEAM, [[1.0, 1.0], [-1.0, 1.0]])
    a = ev.act(obs, env)
    _place(env, [[1.1, 1.0], [0.9, 1.0], [-1.1, 1.0], [-0.9, 1.2]], [[1.0, 1.0], [-1.0, 1.0]])
    np.testing.assert_allclose(ev.act(obs, env), a)


def test_hider_heads_behind_the_obstacle_and_bolts_when_close():
    env, obs = _env(b=1, spec=SwarmSpec.from_dict({"team": {"n_pursuers": 3, "n_scouts": 1, "n_evaders": 2},
                                                   "arena": {"n_obstacles": 1}}))
    ev = make_suite_evader("hider", 0)
    ev.act(obs, env)
    # the threat west of the obstacle at the origin; the evader north-east of it: the spot is due east
    team = [[-2.0, 0.0], [-2.5, 2.5], [-2.5, -2.5], [-2.6, 0.0]]
    _place(env, team, [[0.6, 0.9], [0.5, -2.5]])
    a = ev.act(obs, env)[0, NT]
    spot = np.array([0.4 + SPEC.evader.radius + ev.p["standoff"][0, 0], 0.0])
    to_spot = spot - np.array([0.6, 0.9])
    assert a @ to_spot / np.linalg.norm(to_spot) / np.linalg.norm(a) > 0.9
    team[0] = [0.6, 0.7]  # a pursuer 0.2 m away: panic, straight away from it
    _place(env, team, [[0.6, 0.9], [0.5, -2.5]])
    a = ev.act(obs, env)[0, NT]
    assert a[1] > 0.9 * np.linalg.norm(a)


def test_juker_alternates_its_side():
    env, obs = _env(b=1)
    ev = make_suite_evader("juker", 0)
    ev.act(obs, env)
    period, phase = ev.p["period"][0, 0], ev.p["phase"][0, 0]
    team = [[-1.0, 0.0], [-2.5, 2.5], [-2.5, -2.5], [-2.6, 0.0]]
    side_of = {}
    for step in range(1, 60):  # the first step of each half period
        side_of.setdefault(int((step + phase) // period) % 2, step)
    ys = []
    for step in side_of.values():
        _place(env, team, [[0.0, 0.0], [2.0, 2.0]], obstacles=((0.0, 2.5, 0.3),), step=step)
        a = ev.act(obs, env)[0, NT]
        assert a[0] > 0  # still away from the threats in the west
        angle = np.degrees(np.arctan2(a[1], a[0]))
        assert 25 < abs(angle) < 75  # turned by the drawn angle (30-70 degrees)
        ys.append(np.sign(a[1]))
    assert sorted(ys) == [-1.0, 1.0]


def test_perimeter_runner_keeps_to_the_walls():
    env, obs = _env(b=8, seed=2)
    ev = make_suite_evader("perimeter", 0)
    pol = TeamPolicy(ClassicalPursuers(), ev)
    for _ in range(30):
        obs, *_ = env.step(pol.act(obs, env))
    ep = env.state.pos[:, NT:]
    wall_gap = SPEC.arena.half_width - np.abs(ep).max(-1)
    assert np.median(wall_gap - ev.p["inset"]) < 0.3


def test_predictive_fleer_runs_from_a_threat():
    env, obs = _env(b=1)
    ev = make_suite_evader("predictive", 0)
    ev.act(obs, env)
    _place(env, [[-0.5, 0.0], [-2.5, 2.5], [-2.5, -2.5], [-2.6, 0.0]], [[0.0, 0.0], [2.0, -2.0]],
           obstacles=((0.0, 2.5, 0.3),))
    a = ev.act(obs, env)[0, NT]
    assert a[0] > 0.5 * np.linalg.norm(a)


def test_training_pool_resamples_only_what_it_is_told_and_only_once():
    env, obs = _env(b=64, seed=3)
    pool = TrainingPool(seed=0)
    a = pool.act(obs, env)
    assert (a[:, :NT] == 0).all()
    counts = pool.counts()
    assert set(counts) == set(POOL) and all(c > 0 for c in counts.values())
    obs, *_ = env.step(a)
    before = pool.choice.copy()
    dodger = pool.behaviours[pool.kinds.index("dodger")]
    trig = dodger.p["trigger"].copy()
    pool.resample([0, 1, 2, 3, 4, 5, 6, 7])
    pool.act(obs, env)
    assert (pool.choice[8:] == before[8:]).all()  # others keep their behaviour
    assert (dodger.p["trigger"][8:] == trig[8:]).all() and (dodger.p["trigger"][:8] != trig[:8]).all()
    # an env reset right after resample draws once (resample then act at step 0), not twice
    env2, obs2 = _env(b=64, seed=3)
    p1, p2 = TrainingPool(seed=1), TrainingPool(seed=1)
    p1.act(obs2, env2), p2.act(obs2, env2)
    p1.resample(np.arange(64))
    env2.state.step[:] = 0
    p1.act(obs2, env2)
    p2.resample(np.arange(64))
    np.testing.assert_array_equal(p1.choice, p2.choice)
    with pytest.raises(ValueError, match="unknown training pool kind"):
        TrainingPool(0, kinds=["wanderer"])  # a held-out behaviour cannot be trained against
