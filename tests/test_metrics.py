import numpy as np
import pytest

from runtime.metrics import METRIC_KEYS, MetricsAccumulator, summarize
from runtime.spec import SwarmSpec


def _spec(**arena):
    return SwarmSpec.from_dict({"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 2},
                                "arena": {"n_obstacles": 0, **arena}})


def _no_contacts(b, n):
    return np.zeros((b, n, n), dtype=bool)


def _begin(acc, b, obstacle_pos=None, obstacle_radius=None):
    if obstacle_pos is None:
        obstacle_pos, obstacle_radius = np.zeros((b, 0, 2)), np.zeros((b, 0))
    acc.begin_episodes(np.arange(b), obstacle_pos, obstacle_radius)


def test_distances_and_tracking_on_hand_built_states():
    spec = _spec()
    acc = MetricsAccumulator(spec, 1)
    _begin(acc, 1)
    # agents: pursuer 0, pursuer 1, scout, evader 0, evader 1
    step1 = np.array([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.2], [0.0, 0.3], [2.0, 0.0]]])
    # the scout sits 0.2 m from evader 1 (scouts neither track nor count in the distances: the max would
    # be 2.0025 with it) and 2.0025 m from evader 0
    step2 = np.array([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.2], [0.0, 2.0], [1.0, 0.4]]])
    for pos in (step1, step2):
        acc.update(pos, _no_contacts(1, 5))
    (rec,) = acc.end_episodes(np.array([0]))
    d1 = [0.3, 2.0, np.hypot(1, 0.3), 1.0]
    d2 = [2.0, np.hypot(1, 0.4), np.hypot(1, 2), 0.4]
    assert rec.min_dist == pytest.approx((min(d1) + min(d2)) / 2)
    assert rec.avg_dist == pytest.approx((np.mean(d1) + np.mean(d2)) / 2)
    assert rec.max_dist == pytest.approx((max(d1) + max(d2)) / 2)
    # step 1: evader 0 tracked (0.3 m), evader 1 not (1.0 m); step 2: evader 0 not (2 m), evader 1 (0.4 m)
    assert rec.tracking_rate == pytest.approx(0.5)
    assert rec.steps == 2 and rec.collisions == 0 and rec.captures == 0


def test_episodes_average_per_env_and_summary_has_the_keys():
    spec = _spec()
    acc = MetricsAccumulator(spec, 2)
    _begin(acc, 2)
    pos = np.zeros((2, 5, 2))
    pos[0] = [[0, 0], [0, 1], [-2, -2], [0, 0.5], [0, -0.5]]  # all pursuer-target distances 0.5 or 1.5
    pos[1] = [[0, 0], [0, 1], [-2, -2], [0, 2.0], [0, -1.0]]
    acc.update(pos, _no_contacts(2, 5))
    recs = acc.end_episodes(np.array([0, 1]))
    assert [r.min_dist for r in recs] == pytest.approx([0.5, 1.0])
    assert [r.tracking_rate for r in recs] == pytest.approx([1.0, 0.0])
    s = summarize(recs)
    assert set(METRIC_KEYS) <= set(s)
    assert s["episodes"] == 2 and s["mean_min_dist"] == pytest.approx(0.75) and s["tracking_rate"] == 0.5
    assert summarize([]) == {"episodes": 0}


def test_collisions_and_captures_count_onsets():
    spec = _spec()
    acc = MetricsAccumulator(spec, 1)
    _begin(acc, 1)
    pos = np.zeros((1, 5, 2))
    pursuers_touch = [True, True, False, True, True, False]
    capture = [False, True, True, False, False, True]  # pursuer 0 with evader 0
    evaders_touch = [False, False, True, False, False, False]
    obstacle = [[False, True, True, False, True, False]]  # agent 2 (the scout) touching an obstacle
    for t in range(6):
        c = np.zeros((1, 5, 5), dtype=bool)
        c[0, 0, 1] = pursuers_touch[t]
        c[0, 0, 3] = capture[t]
        c[0, 3, 4] = evaders_touch[t]
        c = c | c.transpose(0, 2, 1)
        o = np.zeros((1, 5), dtype=bool)
        o[0, 2] = obstacle[0][t]
        acc.update(pos, c, o)
    (rec,) = acc.end_episodes(np.array([0]))
    # onsets: pursuer pair at t=0 and t=3, evader pair at t=2, obstacle at t=1 and t=4
    assert rec.collisions == 2 + 1 + 2
    # capture onsets at t=1 and t=5
    assert rec.captures == 2
    # the split: the pursuer pair is teammates', the scout's obstacle touches the team's, the evader pair theirs
    assert (rec.teammate, rec.team_obstacle, rec.evader, rec.team_contacts) == (2, 2, 1, 4)


def test_contacts_split_by_whose_fault_on_hand_built_states():
    """Agents: pursuers 0-1, scout 2, evaders 3-4. Every kind of contact from real positions, one at a time."""
    spec = SwarmSpec.from_dict({"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 2},
                                "arena": {"n_obstacles": 1}})
    radius = np.array(spec.per_agent("radius"))
    obstacle_pos, obstacle_radius = np.array([[[0.0, 0.0]]]), np.array([[0.3]])
    acc = MetricsAccumulator(spec, 2)
    _begin(acc, 2, np.repeat(obstacle_pos, 2, 0), np.repeat(obstacle_radius, 2, 0))
    apart = np.array([[-2.0, -2.0], [-2.0, 2.0], [2.0, -2.0], [2.0, 2.0], [2.5, 0.0]])

    def frame(**moves):
        p = apart.copy()
        for i, xy in moves.items():
            p[int(i[1:])] = xy
        return p

    touch = 0.3 + 0.99 * radius  # just inside contact with the obstacle
    gap = 0.99 * (radius[:, None] + radius[None, :])  # just inside contact between two agents
    env0 = [frame(a0=[-1.0, 0.0], a2=[-1.0 + gap[0, 2], 0.0]),   # pursuer 0 touches the scout: teammate
            frame(),
            frame(a1=[0.0, touch[1]]),                           # pursuer 1 on the obstacle: team-obstacle
            frame(a3=[touch[3], 0.0]),                           # evader 0 on the obstacle: evader side
            frame(a3=[1.0, 1.0], a4=[1.0 + gap[3, 4], 1.0]),     # the evaders touch each other: evader side
            frame(a0=[1.0, 1.0], a3=[1.0 + gap[0, 3], 1.0])]     # pursuer 0 on evader 0: a capture, no collision
    env1 = [frame() for _ in env0]
    for a, b in zip(env0, env1):
        pos = np.stack([a, b])
        d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
        contacts = (d <= radius[:, None] + radius[None, :]) & ~np.eye(5, dtype=bool)
        obst = np.linalg.norm(pos - obstacle_pos[:, :1], axis=-1) <= 0.3 + radius
        acc.update(pos, contacts, obst, d)
    rec, quiet = acc.end_episodes(np.array([0, 1]))
    assert (rec.teammate, rec.team_obstacle, rec.evader, rec.captures) == (1, 1, 2, 1)
    assert rec.collisions == 4 and rec.team_contacts == 2
    assert (quiet.collisions, quiet.captures) == (0, 0)
    s = summarize([rec, quiet])
    assert s["teammate_contacts_per_episode"] == 0.5 and s["team_obstacle_contacts_per_episode"] == 0.5
    assert s["evader_contacts_per_episode"] == 1.0 and s["team_contacts_per_episode"] == 1.0
    assert s["collisions_per_episode"] == 2.0 and s["captures_per_episode"] == 0.5


def _brute_force_coverage(spec, frames, obstacle_pos, obstacle_radius, res):
    hw = spec.arena.half_width
    cells = int(np.ceil(2 * hw / res))
    res = 2 * hw / cells
    c = -hw + (np.arange(cells) + 0.5) * res
    cx, cy = np.meshgrid(c, c, indexing="xy")
    free = np.ones_like(cx, dtype=bool)
    for o, r in zip(obstacle_pos, obstacle_radius):
        free &= (cx - o[0]) ** 2 + (cy - o[1]) ** 2 > r * r
    seen = np.zeros_like(free)
    inst = []
    r2 = spec.sensing.sensing_range ** 2
    for pos in frames:
        now = np.zeros_like(free)
        for p in pos:
            now |= (cx - p[0]) ** 2 + (cy - p[1]) ** 2 <= r2
        now &= free
        seen |= now
        inst.append(now.sum() / free.sum())
    return seen.sum() / free.sum(), float(np.mean(inst))


@pytest.mark.parametrize("seed", range(4))
def test_coverage_matches_brute_force_and_excludes_obstacles(seed):
    spec = _spec(half_width=1.5, n_obstacles=1)
    rng = np.random.default_rng(seed)
    res = 0.05
    acc = MetricsAccumulator(spec, 1, resolution=res)
    obstacle_pos, obstacle_radius = np.array([[0.3, -0.2]]), np.array([0.4])
    _begin(acc, 1, obstacle_pos[None], obstacle_radius[None])
    frames = []
    for t in range(6):
        pos = rng.uniform(-1.5, 1.5, (5, 2))
        if t == 0:
            pos[0] = [1.5, 1.5]  # a corner: the disc sticks out of the arena
            pos[1] = [0.3, 0.15]  # next to the obstacle: the disc overlaps it
            pos[2] = [-0.75, 0.35]  # exactly on a cell boundary
        frames.append(pos[:3])  # pursuers and the scout cover, evaders do not
        acc.update(pos[None], _no_contacts(1, 5))
    (rec,) = acc.end_episodes(np.array([0]))
    cov, inst = _brute_force_coverage(spec, frames, obstacle_pos, obstacle_radius, res)
    assert rec.coverage == pytest.approx(cov, abs=1e-12)
    assert rec.coverage_instant == pytest.approx(inst, abs=1e-12)
    assert 0 < rec.coverage < 1


def test_coverage_is_one_when_every_free_cell_was_seen():
    spec = _spec(half_width=1.5, n_obstacles=1)
    acc = MetricsAccumulator(spec, 1)
    _begin(acc, 1, np.array([[[0.0, 0.0]]]), np.array([[0.45]]))
    # sweep the 3 pursuer-team agents over a 0.3 m grid: every free cell centre is within 0.5 m of a point
    grid = np.arange(-1.5, 1.51, 0.3)
    pts = np.array([[x, y] for x in grid for y in grid])
    for k in range(0, len(pts), 3):
        pos = np.zeros((1, 5, 2))
        chunk = pts[k:k + 3]
        pos[0, :len(chunk)] = chunk
        acc.update(pos, _no_contacts(1, 5))
    (rec,) = acc.end_episodes(np.array([0]))
    # cells inside the obstacle were swept over too but are not part of the free area
    assert rec.coverage == 1.0
    assert acc.free[0].sum() < acc.free[0].size
