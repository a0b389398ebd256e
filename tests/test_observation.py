import numpy as np

from runtime.observation import SIGHTING, encode_observations, new_knowledge, update_knowledge
from runtime.spec import Role, SwarmSpec
from runtime.world import World


def _obs(spec, w, k, observers=None):
    s = w.state
    return encode_observations(spec, s.pos, s.vel, s.obstacle_pos, s.obstacle_radius, k,
                               s.step * spec.timing.control_period, observers=observers)


def test_full_observability_fields():
    spec = SwarmSpec()
    w = World(spec, 3, seed=1)
    w.reset()
    for _ in range(5):
        w.step(np.random.default_rng(0).uniform(-1, 1, (3, 12, 2)))
    k = update_knowledge(spec, new_knowledge(spec, 3), w.state.pos, w.state.vel, 0.5)
    o = _obs(spec, w, k)
    lay = spec.layout(Role.PURSUER)
    s = w.state
    assert np.allclose(o[:, :, lay["self_pos"].slice], s.pos)
    tg = o[:, 0, lay["targets"].slice].reshape(3, 2, 6)
    assert np.allclose(tg[..., 0:2], s.pos[:, 10:] - s.pos[:, None, 0])
    assert np.allclose(tg[..., 5], 1.0) and np.allclose(tg[..., 4], 0.0)
    mates = o[:, 0, lay["teammates"].slice].reshape(3, 4, 5)
    d = np.linalg.norm(s.pos[:, 1:10] - s.pos[:, None, 0], axis=-1)
    assert np.allclose(np.linalg.norm(mates[..., :2], axis=-1), np.sort(d, axis=-1)[:, :4])
    ob = o[:, 0, lay["obstacles"].slice].reshape(3, 3, 3)
    surf = np.linalg.norm(ob[..., :2], axis=-1) - ob[..., 2]
    assert (np.diff(surf, axis=-1) >= 0).all()
    # evaders: threats are the nearest pursuer-team agents, layout is shorter and zero padded
    ev = spec.layout(Role.EVADER)
    assert np.all(o[:, 10:, ev.dim:] == 0)
    th = o[:, 10, ev["threats"].slice].reshape(3, 4, 5)
    d = np.linalg.norm(s.pos[:, :10] - s.pos[:, None, 10], axis=-1)
    assert np.allclose(np.linalg.norm(th[..., :2], axis=-1), np.sort(d, axis=-1)[:, :4])


def test_partial_observability_knowledge_relays_with_age():
    spec = SwarmSpec.from_dict({"sensing": {"observability": "partial", "comm_range": 1.0},
                                "arena": {"n_obstacles": 0}, "team": {"n_pursuers": 3, "n_scouts": 0,
                                                                      "n_evaders": 1}})
    pos = np.array([[[0.0, 0.0], [0.9, 0.0], [1.8, 0.0], [-0.3, 0.0]]])  # p0 sees the evader; p1, p2 chain
    vel = np.zeros_like(pos)
    vel[0, 3] = [0.2, 0.1]
    k = new_knowledge(spec, 1)
    update_knowledge(spec, k, pos, vel, 1.0)
    assert k[0, 0, 0, 4] == 1.0 and np.isneginf(k[0, 1:, 0, 4]).all()
    update_knowledge(spec, k, pos + [[[0, 0], [0, 0], [0, 0], [-2, 0]]], vel, 1.1)  # evader gone out of sight
    assert k[0, 1, 0, 4] == 1.0 and np.isneginf(k[0, 2, 0, 4])  # one hop per period
    update_knowledge(spec, k, pos + [[[0, 0], [0, 0], [0, 0], [-2, 0]]], vel, 1.2)
    assert k[0, 2, 0, 4] == 1.0 and np.allclose(k[0, 2, 0, :4], [-0.3, 0, 0.2, 0.1])
    o = encode_observations(spec, pos, vel, np.zeros((1, 0, 2)), np.zeros((1, 0)), k, 1.2)
    t = spec.layout(Role.PURSUER)["targets"]
    assert np.allclose(o[0, 2, t.slice], [-0.3 - 1.8, 0, 0.2, 0.1, 0.2, 1.0])
    # forgotten after target_memory
    o = encode_observations(spec, pos, vel, np.zeros((1, 0, 2)), np.zeros((1, 0)), k, 1.0 + 3.01)
    assert np.allclose(o[0, 2, t.slice], [0, 0, 0, 0, spec.sensing.target_memory, 0])
    # teammates beyond comm range are invisible
    m = spec.layout(Role.PURSUER)["teammates"]
    mates = o[0, 0, m.slice].reshape(-1, 5)
    assert mates[:, 4].sum() == 1 and np.allclose(mates[0, :2], [0.9, 0.0])


def test_single_observer_equals_batch_row():
    spec = SwarmSpec()
    w = World(spec, 2, seed=4)
    w.reset()
    k = update_knowledge(spec, new_knowledge(spec, 2), w.state.pos, w.state.vel, 0.0)
    full = _obs(spec, w, k)
    for i in (0, 7, 11):
        one = _obs(spec, w, k, observers=[i])
        assert np.array_equal(one[:, 0], full[:, i])


# -- the per-drone fast path: runtime.observation.encode_one equals encode_observations bit for bit -----------

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from runtime.observation import OneObserverEncoder, encode_one  # noqa: E402

_CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@st.composite
def _specs(draw: st.DrawFn) -> SwarmSpec:
    """The shipped multi_target and role_based specs, and random team sizes, slot counts and ranges."""
    obsv = draw(st.sampled_from(["full", "partial"]))
    sensing = {"observability": obsv, "share_assignment": draw(st.booleans())}
    which = draw(st.sampled_from(["multi_target", "role_based", "random"]))
    if which != "random":
        base = SwarmSpec.from_toml(_CONFIGS / f"{which}.toml").to_dict()
        base["sensing"] = {**base["sensing"], **sensing}
        return SwarmSpec.from_dict(base)
    n_p, n_s = draw(st.integers(0, 4)), draw(st.integers(0, 4))
    if n_p + n_s == 0:
        n_p = 1
    sensing.update(sensing_range=draw(st.sampled_from([0.5, 1.0, 2.5])), comm_range=draw(st.sampled_from([1.0, 2.0])),
                   target_memory=draw(st.sampled_from([0.5, 3.0])),
                   n_obstacles_observed=draw(st.integers(0, 4)), n_teammates_observed=draw(st.integers(0, 6)),
                   n_threats_observed=draw(st.integers(0, 6)))
    n_e = draw(st.integers(1, 2 if sensing["share_assignment"] else 3))
    return SwarmSpec.from_dict({"team": {"n_pursuers": n_p, "n_scouts": n_s, "n_evaders": n_e},
                                "arena": {"n_obstacles": draw(st.integers(0, 4))}, "sensing": sensing})


def _state(spec: SwarmSpec, seed: int, grid: bool, far: int, nan: bool):
    """Positions on a 0.25 m grid (exact distance ties) or continuous; ``far`` agents 1 km away; sightings fresh,
    old, exactly ``target_memory`` old, never seen, with stale numbers left in unknown rows; random visibility."""
    rng = np.random.default_rng(seed)
    n, k, nt, e = spec.n_agents, spec.arena.n_obstacles, spec.team.n_team, spec.team.n_evaders
    pos = rng.integers(-8, 9, (n, 2)) * 0.25 if grid else rng.uniform(-3, 3, (n, 2))
    pos[rng.permutation(n)[:far]] += 1000.0
    vel = rng.uniform(-1.3, 1.3, (n, 2))
    if nan:
        pos[rng.integers(n), rng.integers(2)] = np.nan
    opos = rng.integers(-8, 9, (k, 2)) * 0.25 if grid else rng.uniform(-3, 3, (k, 2))
    orad = rng.choice([0.25, 0.45], k) if grid else rng.uniform(0.25, 0.45, k)
    t = 5.0
    mem = spec.sensing.target_memory
    kn = rng.uniform(-3, 3, (1, nt, e, SIGHTING))
    kn[..., 4] = rng.choice([t, t - 0.1, t - mem, t - mem - 1.0, -np.inf], (1, nt, e))
    visible = rng.random((1, n, n)) < 0.6
    return pos[None], vel[None], opos[None], orad[None], kn, t, visible


@settings(max_examples=250, deadline=None)
@given(spec=_specs(), seed=st.integers(0, 2 ** 32 - 1), grid=st.booleans(), far=st.integers(0, 3),
       use_visible=st.booleans(), nan=st.sampled_from([False] * 7 + [True]))
def test_encode_one_equals_encode_observations_bitwise(spec, seed, grid, far, use_visible, nan):
    pos, vel, opos, orad, kn, t, visible = _state(spec, seed, grid, far, nan)
    vis = visible if use_visible else None
    want = encode_observations(spec, pos, vel, opos, orad, kn, t, visible=vis)
    out = np.full(spec.max_obs_dim, 7.0)  # stale contents must be overwritten, the padding zeroed
    for i in range(spec.n_agents):
        got = encode_one(spec, pos[0], vel[0], opos[0], orad[0], kn[0], t, i,
                         visible=None if vis is None else visible[0, i].copy(), out=out)
        assert got is out
        if nan:  # NaN payloads may differ between numpy's vector loops and scalar code: compare as values
            np.testing.assert_array_equal(got, want[0, i], err_msg=f"observer {i}")
        else:
            np.testing.assert_array_equal(got.view(np.int64), want[0, i].view(np.int64), err_msg=f"observer {i}")


def test_encode_one_reuses_its_encoder_and_checks_its_inputs():
    spec = SwarmSpec()
    w = World(spec, 1, seed=6)
    w.reset()
    s = w.state
    k = update_knowledge(spec, new_knowledge(spec, 1), s.pos, s.vel, 0.3)
    enc = OneObserverEncoder(spec, 11)
    out = np.zeros(spec.max_obs_dim)
    enc(s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], k[0], 0.3, None, out)
    assert np.array_equal(out, _obs(spec, w, k, observers=[11])[0, 0])
    with pytest.raises(ValueError, match="observer: agent index 12"):
        OneObserverEncoder(spec, 12)
    with pytest.raises(ValueError, match=r"pos: expected a C-contiguous float64 array of shape \(12, 2\)"):
        encode_one(spec, s.pos, s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], k[0], 0.3, 0)
    with pytest.raises(ValueError, match="knowledge: .*shape"):
        encode_one(spec, s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], k, 0.3, 0)
    with pytest.raises(ValueError, match="visible: .*bool"):
        encode_one(spec, s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], k[0], 0.3, 0,
                   visible=np.ones(12))


# -- the shared split (sensing.share_assignment) ---------------------------------------------------------------

from runtime.tomlmap import SpecError  # noqa: E402


def test_assigned_field_is_the_classical_teams_assignment_with_full_observability():
    from training.baselines import assign_targets
    spec = SwarmSpec.from_dict({"team": {"n_pursuers": 5, "n_scouts": 5, "n_evaders": 2},
                                "sensing": {"share_assignment": True}})
    lay = spec.layout(Role.PURSUER)
    assert lay.names()[-1] == "assigned" and lay["assigned"].rows == 2 and spec.obs_dim(Role.EVADER) == \
        SwarmSpec.from_dict({"team": {"n_pursuers": 5, "n_scouts": 5, "n_evaders": 2}}).obs_dim(Role.EVADER)
    w = World(spec, 256, seed=3)
    w.reset()
    s = w.state
    k = update_knowledge(spec, new_knowledge(spec, 256), s.pos, s.vel, 0.0)
    a = _obs(spec, w, k)[..., lay["assigned"].slice]
    want = assign_targets(s.pos[:, :5], s.pos[:, 10:])  # the Hungarian method over every pursuer
    assert np.array_equal(a[:, :5].argmax(-1), want) and (a[:, :5].sum(-1) == 1).all()
    assert (a[:, 5:10] == 0).all()  # scouts take no target
    counts = a[:, :5].sum(1)  # [B, 2]: the split is 2-3 or 3-2
    assert set(map(tuple, counts.astype(int))) <= {(2, 3), (3, 2)}


def test_assigned_field_with_partial_knowledge_and_one_target():
    spec = SwarmSpec.from_dict({"team": {"n_pursuers": 3, "n_scouts": 1, "n_evaders": 2},
                                "sensing": {"observability": "partial", "share_assignment": True}})
    pos = np.array([[[0.0, 0.0], [0.3, 0.0], [2.9, 2.9], [0.0, 0.3], [0.1, 0.1], [-2.9, -2.9]]])
    vel = np.zeros_like(pos)
    k = update_knowledge(spec, new_knowledge(spec, 1), pos, vel, 0.0)  # only evader 0 is within sensing
    lay = spec.layout(Role.PURSUER)
    o = encode_observations(spec, pos, vel, np.zeros((1, 3, 2)) + 9.0, np.full((1, 3), 0.3), k, 0.0)
    a = o[0, :, lay["assigned"].slice]
    assert a[:2].tolist() == [[1.0, 0.0], [1.0, 0.0]] and a[2].tolist() == [0.0, 0.0]  # pursuer 2 knows none
    assert a[3].tolist() == [0.0, 0.0]  # the scout
    one = SwarmSpec.from_dict({"team": {"n_pursuers": 2, "n_scouts": 0, "n_evaders": 1},
                               "sensing": {"share_assignment": True}})
    w = World(one, 1, seed=0)
    w.reset()
    k1 = update_knowledge(one, new_knowledge(one, 1), w.state.pos, w.state.vel, 0.0)
    assert _obs(one, w, k1)[0, :2, one.layout(Role.PURSUER)["assigned"].slice].tolist() == [[1.0], [1.0]]


def test_share_assignment_checks_and_keeps_the_hash_when_off():
    plain = SwarmSpec()
    assert SwarmSpec.from_dict({"sensing": {"share_assignment": False}}).hash == plain.hash
    assert "assigned" not in plain.layout(Role.PURSUER).names()
    assert SwarmSpec.from_dict({"sensing": {"share_assignment": True}}).hash != plain.hash
    with pytest.raises(SpecError, match="sensing.share_assignment: the shared split is defined for at most 2"):
        SwarmSpec.from_dict({"team": {"n_evaders": 3}, "sensing": {"share_assignment": True}})
    with pytest.raises(SpecError, match="sensing.share_assignment: expected true or false"):
        SwarmSpec.from_dict({"sensing": {"share_assignment": 1}})
