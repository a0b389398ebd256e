"""The demo's metrics count contacts as the world (and so evaluation) does."""
import numpy as np

from groundstation.demo_metrics import EpisodeMetrics
from runtime.metrics import MetricsAccumulator
from runtime.spec import SwarmSpec
from runtime.world import World


def _world_summary(spec: SwarmSpec, obstacles: np.ndarray, frames: list[np.ndarray], capture: float) -> dict:
    """Evaluation's way: a world holds the positions; its contacts feed the accumulator (captures by distance)."""
    w = World(spec, n_envs=1)
    w.state.obstacle_pos[0] = obstacles[:, :2]
    w.state.obstacle_radius[0] = obstacles[:, 2]
    acc = MetricsAccumulator(spec, 1)
    acc.begin_episodes(np.array([0]), w.state.obstacle_pos, w.state.obstacle_radius)
    nt = spec.team.n_team
    cross = np.zeros((spec.n_agents, spec.n_agents), dtype=bool)
    cross[:nt, nt:] = cross[nt:, :nt] = True
    for pos in frames:
        w.state.pos[0] = pos
        dist = w.distances()
        contacts = np.where(cross, (dist <= capture) & ~np.eye(spec.n_agents, dtype=bool), w.contacts(dist))
        acc.update(w.state.pos, contacts, w.obstacle_contacts(), dist)
    acc.end_episodes(np.array([0]))
    return acc.summary()


def test_contacts_at_the_worlds_tolerance():
    """An agent a hair (5e-10 m) beyond touching an obstacle touches it for the world (tolerance 1e-9 m): the
    demo's count is the world's, where a plain distance test would miss it."""
    spec = SwarmSpec()
    obstacles = np.array([[0.0, 0.0, 0.4], [2.0, 2.0, 0.3], [-2.0, 2.0, 0.3]])
    r0 = spec.per_agent("radius")[0]
    far = np.stack([np.linspace(-2.5, 2.5, spec.n_agents), np.full(spec.n_agents, -2.5)], axis=1)
    touching = far.copy()
    touching[0] = (0.4 + r0 + 5e-10, 0.0)
    em = EpisodeMetrics(spec, obstacles, capture_distance=0.3)
    present = np.ones(spec.n_agents, dtype=bool)
    for k, pos in enumerate([far, touching, far]):
        em(0.1 * k, pos, np.zeros_like(pos), present)
    got = em.summary()
    assert got["team_obstacle_contacts_per_episode"] == 1.0
    assert got == _world_summary(spec, obstacles, [far, touching, far], 0.3)


def test_random_flights_match_the_world_step_by_step():
    spec = SwarmSpec()
    rng = np.random.default_rng(5)
    w = World(spec, n_envs=1, seed=5)
    s = w.reset()
    obstacles = np.concatenate([s.obstacle_pos[0], s.obstacle_radius[0, :, None]], axis=1)
    frames = []
    for _ in range(60):  # a random walk that crowds the agents together: contacts of every kind
        w.step(rng.uniform(-1, 1, (1, spec.n_agents, 2)))
        frames.append(w.state.pos[0] * 0.3)
    em = EpisodeMetrics(spec, obstacles, capture_distance=0.25)
    present = np.ones(spec.n_agents, dtype=bool)
    for k, pos in enumerate(frames):
        em(0.1 * k, pos, np.zeros_like(pos), present)
    got = em.summary()
    assert got["collisions_per_episode"] > 0
    assert got == _world_summary(spec, obstacles, frames, 0.25)
