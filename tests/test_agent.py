"""runtime.agent: the observation equals the training encoder's on the same state, faults stay in their drone,
clean start and stop, no growth in the steady-state loop."""
from __future__ import annotations

import threading
import time
import tracemalloc

import numpy as np
import pytest

from runtime.agent import Agent, AgentConfig, Perception
from runtime.comms import CommConfig, InProcessBus, Radio
from runtime.observation import encode_observations, new_knowledge, update_knowledge
from runtime.policy import load_models
from runtime.spec import SpecError
from runtime.swarm import WorldBoard, WorldSink, WorldSource
from tests.runtime_fixtures import exported
from training.env import PursuitEnv


@pytest.fixture(scope="module")
def full():
    _, models, _ = exported(False)
    return load_models(models)


@pytest.fixture(scope="module")
def partial(tmp_path_factory):
    # only this module needs partial-observability actors: export them with a short parity check
    from firmware_export.onnx_export import export_run
    from runtime.spec import SwarmSpec
    from tests.runtime_fixtures import make_run
    root = tmp_path_factory.mktemp("partial")
    run = make_run(root / "run", SwarmSpec.from_dict({"sensing": {"observability": "partial"}}), seed=1)
    export_run(run, root / "models", n_random=500, n_recorded=500)
    return load_models(root / "models")


EXACT = CommConfig(exact_values=True)
"""The simulated radio with the sender's float64 values beside the packet: observations bit-identical to training's."""


def make_agents(manifest, policies, board, cfg=None, comms=None, on_fault=None):
    spec = manifest.spec
    bus = InProcessBus(spec.n_agents)
    src, sink = WorldSource(board, spec), WorldSink(board, spec)
    return [Agent(i, spec, policies[i], src, sink, Radio(spec, i, bus.endpoint(i), comms), cfg, on_fault=on_fault)
            for i in range(spec.n_agents)]


def two_rounds(agents):
    """Every agent reads, then every agent acts and broadcasts (what it sensed itself), then every agent reads
    again: each has now heard its neighbours' states and sightings once (one relay hop, as in training)."""
    for a in agents:
        a.prepare()
    for a in agents:
        a.actuate()
    for a in agents:
        a.prepare()


def _seventh_step(spec):
    """Training's observations after 7 random steps of env seed 3, and a board holding that state."""
    env = PursuitEnv(spec, n_envs=1, seed=3)
    obs = env.reset()
    rng = np.random.default_rng(0)
    for _ in range(7):
        obs, *_ = env.step(rng.uniform(-1, 1, (1, spec.n_agents, 2)))
    s = env.state
    board = WorldBoard(spec)
    board.publish(s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], float(env.time_s()[0]), 0)
    return obs, board


def test_observation_equals_the_training_encoder_full_observability(full):
    manifest, policies = full
    spec = manifest.spec
    obs, board = _seventh_step(spec)
    agents = make_agents(manifest, policies, board, comms=EXACT)
    two_rounds(agents)
    for i, a in enumerate(agents):
        d = spec.obs_dim(spec.roles[i])
        np.testing.assert_array_equal(a.obs, obs[0, i, :d], err_msg=a.agent_id)
        assert a.stats.faults == 0


def test_over_the_real_packet_every_agent_hears_its_team_and_sees_within_the_quantization(full):
    """The simulated radio's default carries only the 60-byte packet (int16 fixed point, whole ms): every
    full-observability agent hears all its teammates in one exchange (none left waiting, no all-zero observation)
    and its observation is the training encoder's to within half a step of the packet's scales."""
    from runtime.radio_msg import Scales
    manifest, policies = full
    spec = manifest.spec
    obs, board = _seventh_step(spec)
    assert not CommConfig().exact_values
    agents = make_agents(manifest, policies, board)
    two_rounds(agents)
    sc = Scales.for_spec(spec)
    for i, a in enumerate(agents):
        d = spec.obs_dim(spec.roles[i])
        assert a._ready and a.stats.waiting == 1 and a.stats.faults == 0, a.agent_id  # waited the first round only
        assert np.abs(a.obs).max() > 0
        np.testing.assert_allclose(a.obs, obs[0, i, :d], rtol=0, atol=max(sc.pos_lsb, sc.vel_lsb) / 2 + 1e-9,
                                   err_msg=a.agent_id)


def test_observation_equals_the_training_encoder_partial_observability(partial):
    manifest, policies = partial
    spec = manifest.spec
    nt = spec.team.n_team
    env = PursuitEnv(spec, n_envs=1, seed=5)
    env.reset()
    s = env.state
    # pursuer 0 senses evader 0; scout 5 hears pursuer 0 (in comm range) but senses nothing itself
    s.pos[0, 0] = s.pos[0, nt] + [0.3, 0.0]
    s.pos[0, 5] = s.pos[0, 0] + [0.0, 1.2]
    t = 2.5
    kn = new_knowledge(spec, 1)
    update_knowledge(spec, kn, s.pos, s.vel, t)  # what the world knows after a read...
    update_knowledge(spec, kn, s.pos, s.vel, t)  # ...and after one relay hop at the same state
    want = encode_observations(spec, s.pos, s.vel, s.obstacle_pos, s.obstacle_radius, kn, t)
    assert want[0, 5, spec.layout(spec.roles[5])["targets"].slice].any()  # the relayed sighting is in it
    board = WorldBoard(spec)
    board.publish(s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], t, 0)
    agents = make_agents(manifest, policies, board, comms=EXACT)
    two_rounds(agents)
    for i, a in enumerate(agents):
        d = spec.obs_dim(spec.roles[i])
        np.testing.assert_array_equal(a.obs, want[0, i, :d], err_msg=a.agent_id)


class Exploding:
    """A policy that raises, as a broken model or driver would."""

    def __init__(self, inner):
        self.inner, self.role, self.faults, self.last_fault = inner, inner.role, 0, ""

    def act(self, obs, out=None):
        raise RuntimeError("actor exploded")


def test_a_fault_in_one_agent_never_stops_the_others(full):
    manifest, policies = full
    spec = manifest.spec
    env = PursuitEnv(spec, n_envs=1, seed=1)
    env.reset()
    s = env.state
    board = WorldBoard(spec)
    board.publish(s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], 0.0, 0)
    board.cmd[:] = 0.5
    faults: list[tuple[int, str]] = []
    pols = list(policies)
    pols[4] = Exploding(policies[4])
    agents = make_agents(manifest, pols, board, AgentConfig(rate_hz=50.0, lead_s=0.002),
                         on_fault=lambda i, m: faults.append((i, m)))
    t0 = time.monotonic() + 0.05
    for i, a in enumerate(agents):
        a.config = a.config  # noqa: PLW0127 (same config; phases below)
        a.start(t0 + i * 0.02 / len(agents))
    time.sleep(0.6)
    assert all(a.running for a in agents)
    assert all(a.stop() for a in agents)
    assert not any(a.running for a in agents)
    bad = agents[4]
    assert bad.stats.faults >= 20 and bad.stats.actions == 0
    assert "actor exploded" in bad.stats.last_fault
    assert {i for i, _ in faults} == {4}
    for a in agents[:4] + agents[5:]:
        assert a.stats.faults == 0, (a.agent_id, a.stats.last_fault)
        assert 20 <= a.stats.ticks <= 32 and a.stats.actions >= a.stats.ticks - 3
    np.testing.assert_array_equal(board.cmd[4], [0.0, 0.0])  # the safe action
    np.testing.assert_array_equal(board.cmd, 0.0)  # and every drone holds after stop


def test_non_finite_state_and_missing_state_give_the_safe_action(full):
    manifest, policies = full
    spec = manifest.spec
    sent: list[np.ndarray] = []
    mode = {"v": "nan"}

    def source(i: int, p: Perception) -> bool:
        if mode["v"] == "none":
            return False
        p.pos[:] = [0.0, np.nan] if mode["v"] == "nan" else [0.5, 0.5]
        p.vel[:] = 0.0
        p.sensed[:] = False
        p.sensed[spec.team.n_team:] = True
        p.others_pos[:] = 1.0
        p.time_s = 1.0
        return True

    a = Agent(0, spec, policies[0], source, lambda i, v: sent.append(v.copy()), radio=None)
    a.neighbours.t_state[:] = 0.0  # as if every teammate had been heard
    a.tick()
    np.testing.assert_array_equal(sent[-1], 0.0)
    assert a.stats.faults == 1 and "non-finite" in a.stats.last_fault
    mode["v"] = "none"
    a.tick()
    np.testing.assert_array_equal(sent[-1], 0.0)
    assert a.stats.no_state == 1 and a.stats.faults == 2
    assert a.stats.last_fault == "no fresh state from the state source"
    source.why_not = lambda i: f"drone cf{i} is not flying"  # a source that can say why: the message ends with it
    a.tick()
    np.testing.assert_array_equal(sent[-1], 0.0)
    assert a.stats.last_fault == "no fresh state from the state source: drone cf0 is not flying"
    assert a.stats.no_state == 2 and a.stats.faults == 3
    mode["v"] = "ok"
    v = a.tick()
    assert np.linalg.norm(v) <= spec.role(spec.roles[0]).max_speed + 1e-9 and a.stats.faults == 3
    assert a.stats.ticks == 4 and a.stats.actions == 2


def test_policy_of_the_wrong_role_is_refused(full):
    manifest, policies = full
    with pytest.raises(SpecError, match="flies as a pursuer"):
        Agent(0, manifest.spec, policies[-1], lambda i, p: False, lambda i, v: None)


def test_steady_state_loop_does_not_grow_memory(full):
    manifest, policies = full
    spec = manifest.spec
    env = PursuitEnv(spec, n_envs=1, seed=2)
    env.reset()
    s = env.state
    board = WorldBoard(spec)
    agents = make_agents(manifest, policies, board, comms=CommConfig(latency_s=0.05, loss=0.2))
    clock = {"t": 0.0}
    for a in agents:
        a.clock = lambda: clock["t"]

    def run(n):
        for _ in range(n):
            clock["t"] += 0.01
            board.publish(s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], clock["t"], 0)
            for a in agents:
                a.tick()

    run(30)
    tracemalloc.start()
    try:
        run(10)
        base = tracemalloc.get_traced_memory()[0]
        run(60)
        grown = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert grown < 4096, f"the steady-state loop kept {grown} B over 60 ticks of 12 agents"
    assert all(a.stats.faults == 0 for a in agents)


def test_start_twice_is_refused_and_stop_is_prompt(full):
    manifest, policies = full
    spec = manifest.spec
    calls = threading.Event()
    a = Agent(0, spec, policies[0], lambda i, p: calls.set() or False, lambda i, v: None,
              config=AgentConfig(rate_hz=2.0))
    a.start()
    with pytest.raises(RuntimeError, match="already started"):
        a.start()
    assert calls.wait(2.0)
    t = time.monotonic()
    assert a.stop() and time.monotonic() - t < 0.2


def test_an_unchanged_state_reuses_the_observation_and_a_changed_one_rebuilds_it(full):
    manifest, policies = full
    spec = manifest.spec
    env = PursuitEnv(spec, n_envs=1, seed=4)
    obs = env.reset()
    s = env.state
    board = WorldBoard(spec)
    board.publish(s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], 0.0, 0)
    # reuse applies to the reference encoder (the fast one always builds: cheaper than the comparison)
    agents = make_agents(manifest, policies, board, AgentConfig(broadcast_period_s=0.0, fast_encoder=False),
                         comms=EXACT)
    two_rounds(agents)
    for a in agents:
        a.prepare()  # same state, nothing new heard: the encoder is skipped
    for i, a in enumerate(agents):
        assert a.stats.reused == 1
        np.testing.assert_array_equal(a.obs, obs[0, i, :spec.obs_dim(spec.roles[i])])
    obs, *_ = env.step(np.full((1, spec.n_agents, 2), 0.5))
    board.publish(s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], float(env.time_s()[0]), 0)
    two_rounds(agents)
    for i, a in enumerate(agents):
        assert a.stats.reused == 1  # the state moved, then the teammates' messages: rebuilt both times
        np.testing.assert_array_equal(a.obs, obs[0, i, :spec.obs_dim(spec.roles[i])])


def test_fast_and_reference_encoders_give_the_same_observations_and_actions(partial):
    """Two swarms on the same moving world, one on the numba one-observer encoder, one on encode_observations:
    bit-identical observations and commands at every tick (partial observability: visibility, relayed and
    aging sightings, teammates dropping out of comm range)."""
    manifest, policies = partial
    spec = manifest.spec
    env = PursuitEnv(spec, n_envs=1, seed=8)
    env.reset()
    s = env.state
    boards = [WorldBoard(spec), WorldBoard(spec)]
    swarms = [make_agents(manifest, policies, b, AgentConfig(fast_encoder=fast))
              for b, fast in zip(boards, (True, False))]
    assert swarms[0][0]._encoder is not None and swarms[1][0]._encoder is None
    clock = {"t": 0.0}
    for a in swarms[0] + swarms[1]:
        a.clock = lambda: clock["t"]
    rng = np.random.default_rng(1)
    for _ in range(25):
        clock["t"] += spec.timing.control_period
        for b in boards:
            b.publish(s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], clock["t"], 0)
        for fast, slow in zip(*swarms):
            v = fast.tick().copy()
            np.testing.assert_array_equal(slow.tick(), v, err_msg=fast.agent_id)
            np.testing.assert_array_equal(fast.obs.view(np.int64), slow.obs.view(np.int64), err_msg=fast.agent_id)
        env.step(rng.uniform(-1, 1, (1, spec.n_agents, 2)))
    assert all(a.stats.actions > 0 and a.stats.faults == 0 for a in swarms[0] + swarms[1])
