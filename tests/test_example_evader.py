"""examples/evaders/gap_runner.py: the user-evader example, loaded the way --evader loads it, and its geometry."""
import importlib.util
import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from runtime.spec import SwarmSpec
from training.baselines import ClassicalPursuers, TeamPolicy
from training.env import PursuitEnv
from training.evader_spec import expand, label, make_evaders
from training.evader_suite import POOL, SUITE

PATH = Path(__file__).resolve().parents[1] / "examples" / "evaders" / "gap_runner.py"
SPEC = SwarmSpec.from_dict({"team": {"n_pursuers": 3, "n_scouts": 1, "n_evaders": 2},
                            "timing": {"episode_steps": 40}})
NT = SPEC.team.n_team


def _module():
    mspec = importlib.util.spec_from_file_location("gap_runner_under_test", PATH)
    mod = importlib.util.module_from_spec(mspec)
    mspec.loader.exec_module(mod)
    return mod


def _reference_gap(bearings, active):
    """The widest gap by brute force: every active bearing as the gap's start, the next one counter-clockwise."""
    two_pi = 2 * math.pi
    angs = [b % two_pi for b, a in zip(bearings, active) if a]
    if not angs:
        return None
    if len(angs) == 1:
        return two_pi, (angs[0] + math.pi) % two_pi
    best = (-1.0, 0.0)
    for a in angs:
        nxt = min((b - a) % two_pi for b in angs if (b - a) % two_pi > 0)
        best = max(best, (nxt, (a + nxt / 2) % two_pi))
    return best


def test_widest_gap_matches_a_brute_force_reference():
    widest_gap = _module().widest_gap
    rng = np.random.default_rng(0)
    bearings = rng.uniform(-4, 4, (500, 7))
    active = rng.random((500, 7)) < 0.5
    mid, width = widest_gap(bearings, active)
    for i in range(500):
        ref = _reference_gap(bearings[i], active[i])
        if ref is None:
            assert width[i] == 0 and mid[i] == 0
            continue
        assert width[i] == pytest.approx(ref[0], abs=1e-12)
        # the same gap (ties between equally wide gaps do not occur with random bearings)
        assert abs((mid[i] - ref[1] + math.pi) % (2 * math.pi) - math.pi) < 1e-9


def test_it_loads_through_evader_and_follows_the_protocol_with_paired_parameters():
    spec = f"{PATH}:GapRunner"
    assert expand(spec) == [spec] and label(spec) == spec
    env = PursuitEnv(SPEC, n_envs=4, seed=0)
    obs = env.reset()
    a, b = make_evaders(spec, 3), make_evaders(spec, 3)
    other = make_evaders(spec, 4)
    moved = 0.0
    for _ in range(45):  # through one automatic reset
        act = a.act(obs, env)
        assert act.shape == (4, SPEC.n_agents, 2) and np.isfinite(act).all()
        assert (act[:, :NT] == 0).all() and (np.linalg.norm(act[:, NT:], axis=-1) <= 1 + 1e-9).all()
        np.testing.assert_array_equal(b.act(obs, env), act)  # the learned and the classical column meet the same
        moved += np.linalg.norm(act[:, NT:], axis=-1).mean()
        team = ClassicalPursuers().act(obs, env)
        team[:, NT:] = act[:, NT:]
        obs, *_ = env.step(team)
    assert moved / 45 > 0.3
    assert not np.array_equal(other.act(obs, env), a.act(obs, env))  # another seed, other parameters


def test_it_is_neither_a_suite_kind_nor_a_pool_kind():
    name = _module().GapRunner.name
    assert name not in SUITE and name not in POOL
    assert not any(issubclass(_module().GapRunner, c) for c in itertools.chain(SUITE.values(), POOL.values()))


def _place(env, team_pos, evader_pos):
    s = env.state
    s.pos[:, :NT] = team_pos
    s.pos[:, NT:] = evader_pos
    s.vel[:] = 0
    s.obstacle_pos[:] = np.array([[2.5, 2.5], [2.5, 1.5], [1.5, 2.5]])[None]  # out of the way
    s.obstacle_radius[:] = 0.25
    s.step[:] = 5


def test_it_breaks_out_between_two_pursuers_instead_of_into_the_wall():
    env = PursuitEnv(SPEC, n_envs=1, seed=0)
    obs = env.reset()
    ev = _module().GapRunner(seed=0)
    ev.act(obs, env)  # draws the parameters at step 0
    # the evader 0.2 m off the south wall; two pursuers 1 m away at 20 and 160 degrees: a fleer runs south into
    # the wall; the widest gap (140 degrees, between the pursuers) is due north
    e = np.array([0.0, -2.8])
    threats = [e + [math.cos(math.radians(t)), math.sin(math.radians(t))] for t in (20, 160)]
    _place(env, [*threats, [-2.5, 2.5], [-2.6, 2.0]], [e, [2.0, 0.0]])
    a = ev.act(obs, env)[0, NT]
    assert a[1] > 0.95 * np.linalg.norm(a) and np.linalg.norm(a) > 0.8
    # nobody within its awareness (at most 3 m): a slow drift towards its own spot
    _place(env, [[-2.5, 2.5], [-2.6, 2.5], [-2.5, 2.6], [-2.6, 2.6]], [[2.0, -2.0], [2.0, 0.0]])
    a = ev.act(obs, env)[0, NT]
    to_spot = ev.p["spot"][0, 0] - np.array([2.0, -2.0])
    assert 0.15 < np.linalg.norm(a) <= 0.5 + 1e-9
    assert a @ to_spot / np.linalg.norm(a) / np.linalg.norm(to_spot) > 0.9
