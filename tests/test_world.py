import numpy as np
import pytest

from runtime.spec import SwarmSpec
from runtime.world import World


def _inside_everything(w: World):
    s = w.state
    hw = w.half_width
    assert (np.abs(s.pos) <= hw - w.radius[None, :, None] + 1e-9).all()
    d = np.linalg.norm(s.pos[:, :, None] - s.obstacle_pos[:, None], axis=-1)
    assert (d >= s.obstacle_radius[:, None] + w.radius[None, :, None] - 1e-9).all()


def test_reset_places_everything_validly():
    spec = SwarmSpec()
    w = World(spec, n_envs=512, seed=3)
    s = w.reset()
    _inside_everything(w)
    # obstacles do not overlap and keep their clearance
    c, r = s.obstacle_pos, s.obstacle_radius
    for i in range(3):
        for j in range(i):
            gap = np.linalg.norm(c[:, i] - c[:, j], axis=-1) - r[:, i] - r[:, j]
            assert (gap >= spec.arena.obstacle_clearance - 1e-9).all()
    assert (np.abs(c) + r[..., None] <= spec.arena.half_width - spec.arena.obstacle_clearance + 1e-9).all()
    assert (r >= spec.arena.obstacle_radius_min).all() and (r <= spec.arena.obstacle_radius_max).all()
    # nobody starts in contact with anybody
    assert not w.contacts().any()
    assert (s.vel == 0).all() and (s.step == 0).all()


def test_random_walks_never_leave_the_arena_or_enter_obstacles():
    w = World(SwarmSpec(), n_envs=64, seed=0)
    w.reset()
    rng = np.random.default_rng(1)
    for _ in range(300):
        # adversarial: full speed towards the nearest obstacle or a wall, and random
        a = rng.choice([-1.0, 1.0], size=(64, w.n_agents, 2)) if rng.random() < 0.5 else \
            np.sign(w.state.obstacle_pos[:, :1] - w.state.pos)
        w.step(a)
        _inside_everything(w)


def test_speed_and_acceleration_limits():
    spec = SwarmSpec()
    w = World(spec, n_envs=8, seed=0)
    w.reset()
    prev = w.state.vel.copy()
    for _ in range(15):
        w.step(np.ones((8, w.n_agents, 2)))
        v = w.state.vel
        assert (np.linalg.norm(v, axis=-1) <= w.max_speed + 1e-9).all()
        # walls and obstacles stop an agent abruptly; elsewhere the acceleration limit holds
        free = (np.abs(w.state.pos) < w.half_width - w.radius[None, :, None] - 1e-6).all(-1)
        free &= ~w.obstacle_contacts()
        dv = np.linalg.norm(v - prev, axis=-1)
        assert free.sum() > 50 and (dv <= w.max_accel * w.dt + 1e-9)[free].all()
        prev = v.copy()
    # evaders are 30% faster: compare top speeds reached in free flight
    spec0 = SwarmSpec.from_dict({"arena": {"n_obstacles": 0}})
    w = World(spec0, 1, seed=0)
    w.reset()
    w.state.pos[:] = 0.0
    for _ in range(10):
        w.state.pos[:] = 0.0
        w.step(np.tile([[1.0, 0.0]], (1, w.n_agents, 1)))
    sp = np.linalg.norm(w.state.vel[0], axis=-1)
    assert sp[-1] == pytest.approx(1.3 * sp[0])


def test_same_seed_same_trajectory_and_partial_reset():
    def run(seed):
        w = World(SwarmSpec(), n_envs=4, seed=seed)
        w.reset()
        rng = np.random.default_rng(seed)
        traj = []
        for t in range(50):
            w.step(rng.uniform(-1, 1, (4, w.n_agents, 2)))
            if t == 20:
                w.reset(np.array([1, 3]))
            traj.append(w.state.pos.copy())
        return np.array(traj)
    a, b, c = run(5), run(5), run(6)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_partial_reset_touches_only_chosen_envs():
    w = World(SwarmSpec(), n_envs=4, seed=0)
    w.reset()
    for _ in range(5):
        w.step(np.ones((4, w.n_agents, 2)))
    before = w.state.copy()
    w.reset(np.array([2]))
    assert np.array_equal(w.state.pos[[0, 1, 3]], before.pos[[0, 1, 3]])
    assert w.state.step[2] == 0 and (w.state.step[[0, 1, 3]] == 5).all()
    assert not np.array_equal(w.state.obstacle_pos[2], before.obstacle_pos[2])


def test_nonfinite_actions_never_enter_the_state():
    w = World(SwarmSpec(), n_envs=2, seed=0)
    w.reset()
    a = np.zeros((2, w.n_agents, 2))
    a[0, 0] = [np.nan, 0.5]
    a[1, 3] = [np.inf, -np.inf]
    w.step(a)
    assert np.isfinite(w.state.pos).all() and np.isfinite(w.state.vel).all()
    assert w.nonfinite_actions == 2
    with pytest.raises(ValueError, match="shape"):
        w.step(np.zeros((2, 3, 2)))


def test_single_env_runs_the_same_code():
    w1 = World(SwarmSpec(), n_envs=1, seed=9)
    w1.reset()
    w1.step(np.full((1, w1.n_agents, 2), 0.3))
    assert w1.state.pos.shape == (1, 12, 2)


def test_contacts_detected():
    w = World(SwarmSpec.from_dict({"arena": {"n_obstacles": 0}}), n_envs=1, seed=0)
    w.reset()
    w.state.pos[0, :] = np.stack([np.linspace(-2.5, 2.5, 12), np.zeros(12)], -1)
    w.state.pos[0, 10] = w.state.pos[0, 0] + [0.075 + 0.05, 0.0]  # evader exactly touching pursuer 0
    c = w.contacts()
    assert c[0, 0, 10] and c[0, 10, 0] and c.sum() == 2


def test_one_action_to_velocity_for_the_world_and_each_drone():
    """The world's batch and a drone's runtime (one agent, ``[1, 2]``) turn an action into the same velocity, to
    the bit: action x max speed, the norm limited to the max speed."""
    from runtime.world import action_to_velocity
    spec = SwarmSpec()
    ms = np.array(spec.per_agent("max_speed"))
    rng = np.random.default_rng(2)
    a = rng.uniform(-1, 1, (64, spec.n_agents, 2))
    a[:, :, :] = np.where(rng.random((64, spec.n_agents, 1)) < 0.3, np.sign(a), a)  # corners: over the limit
    a32 = a.astype(np.float32)  # a policy's output
    a = a32.astype(np.float64)
    v = action_to_velocity(ms, a)
    speed = np.linalg.norm(v, axis=-1)
    assert (speed <= ms[None] * (1 + 1e-15)).all()
    inside = np.linalg.norm(a, axis=-1) <= 1.0
    assert np.array_equal(v[inside], (a * ms[None, :, None])[inside])
    over = ~inside
    assert over.any() and np.allclose(speed[over], np.broadcast_to(ms, speed.shape)[over], rtol=1e-15)
    one = np.zeros((1, 2))
    for b in range(0, 64, 7):
        for i in range(spec.n_agents):
            action_to_velocity(np.array([ms[i]]), a32[b, i][None], out=one)  # as runtime.agent calls it
            assert np.array_equal(one[0], v[b, i])
