import numpy as np

from runtime.observation import encode_observations, new_knowledge, update_knowledge
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
