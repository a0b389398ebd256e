"""What the demo and a fleet flight measure while they fly: the paper's metrics from the drones' measured
positions (``EpisodeMetrics``), and the closest two simulated drones came (``PairMonitor``, ground truth)."""
from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from runtime.metrics import MetricsAccumulator
from runtime.spec import SwarmSpec
from runtime.world import World, WorldState

LANDED_Z = 0.05
"""A simulated drone at or below this height with its motors off has landed [m] (``landed``; ``locked`` counts
those of them whose firmware cut the motors instead: a watchdog after link loss, or an emergency stop)."""


def on_ground(truth) -> bool:
    """A simulated drone (its ground truth) is down with its motors off."""
    return truth.position[2] <= LANDED_Z and not truth.motors_on


class EpisodeMetrics:
    """``runtime.metrics`` over the flight: one episode per ``spec.timing.episode_steps`` control periods (a
    shorter last episode counts too). Agents are the actors in spec order at the measured position of the
    drone flying each; an actor left without a drone stays where its last drone was (and takes no part in
    contacts). A capture is the onset of a pursuer-team agent within ``capture_distance`` of an evader.

    Distances, teammate contacts and obstacle contacts are the world's (``runtime.world.World`` holding the
    measured positions and the flight's obstacles): the same rule and tolerance as training and evaluation."""

    def __init__(self, spec: SwarmSpec, obstacles: np.ndarray, capture_distance: float | None = None) -> None:
        self.spec = spec
        self.capture_distance = spec.sensing.sensing_range if capture_distance is None else capture_distance
        nt = spec.team.n_team
        self.cross = np.zeros((spec.n_agents, spec.n_agents), dtype=bool)
        self.cross[:nt, nt:] = self.cross[nt:, :nt] = True
        self._others = ~np.eye(spec.n_agents, dtype=bool)
        self.acc = MetricsAccumulator(spec, 1)
        obstacles = np.asarray(obstacles, dtype=float).reshape(-1, 3)
        self.world = World(spec, n_envs=1)
        """Holds the measured positions; the flight's obstacles (any number: a fleet file's keep-outs) replace
        the spec's drawn ones."""
        self.world.state = WorldState(np.zeros((1, spec.n_agents, 2)), np.zeros((1, spec.n_agents, 2)),
                                      obstacles[None, :, :2].copy(), obstacles[None, :, 2].copy(),
                                      np.zeros(1, dtype=np.int64))
        self.steps = 0
        self.trail: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._lock = threading.Lock()
        self._begin()

    def _begin(self) -> None:
        s = self.world.state
        self.acc.begin_episodes(np.array([0]), s.obstacle_pos, s.obstacle_radius)

    def __call__(self, t: float, pos: np.ndarray, vel: np.ndarray, present: np.ndarray) -> None:
        with self._lock:
            w = self.world
            w.state.pos[0] = pos
            dist = w.distances()
            # pursuer-team x evader pairs "touch" (a capture) within capture distance; other pairs on contact
            contacts = np.where(self.cross, (dist <= self.capture_distance) & self._others, w.contacts(dist))
            contacts &= present[None, :, None] & present[None, None, :]
            obst = w.obstacle_contacts() & present[None]
            self.acc.update(w.state.pos, contacts, obst, dist)
            self.steps += 1
            self.trail.append((t, pos.copy(), present.copy()))
            if self.steps % self.spec.timing.episode_steps == 0:
                self.acc.end_episodes(np.array([0]))
                self._begin()

    def summary(self) -> dict[str, float]:
        with self._lock:
            if self.steps % self.spec.timing.episode_steps:
                self.acc.end_episodes(np.array([0]))
            return self.acc.summary()

    def live(self) -> dict[str, float]:
        """The metrics so far, the running episode included (left open), for the live view: every finished
        episode and the running one weigh the same, as in ``summary``."""
        with self._lock:  # a copy of a few numbers: the control thread's update waits microseconds at most
            acc = self.acc
            sums, steps = acc._sums[0].copy(), float(acc._sums[0, 5])
            coverage = float((acc.visited[0] & acc.free[0]).sum() / acc.free_count[0]) if steps else None
            records = list(acc.records)
            captures = int(acc._captures[0]) + sum(r.captures for r in records)
            n = self.steps
        rows = [(r.min_dist, r.avg_dist, r.max_dist, r.tracking_rate, r.coverage) for r in records]
        if steps:
            m = sums / steps
            rows.append((m[0], m[1], m[2], m[3], coverage))
        out: dict[str, Any] = {"episodes": len(records), "steps": n, "captures": captures}
        if rows:
            avg = np.mean(np.array(rows, dtype=float), axis=0)
            out.update({k: round(float(v), 4) for k, v in zip(("mean_min_dist", "mean_avg_dist", "mean_max_dist",
                                                               "tracking_rate", "coverage"), avg)})
            if steps:
                out["coverage_instant"] = round(float(sums[4] / steps), 4)
        return out


class PairMonitor:
    """The closest two airborne simulated drones came (ground truth, centre to centre, 3-D) during the mission,
    and how many times a pair came closer than ``min_distance`` or within ``contact`` (onsets)."""

    def __init__(self, min_distance: float, contact: float) -> None:
        self.min_distance, self.contact = min_distance, contact
        self.closest = math.inf
        self.below = 0
        self.touching = 0
        self.samples = 0
        self._below: np.ndarray | None = None
        self._touch: np.ndarray | None = None

    def update(self, truths: list) -> None:
        p = np.array([t.position for t in truths])
        up = np.array([t.motors_on and t.position[2] > LANDED_Z for t in truths])
        d = np.linalg.norm(p[:, None] - p[None], axis=-1)
        pair = up[:, None] & up[None] & ~np.eye(len(p), dtype=bool)
        below, touch = (d < self.min_distance) & pair, (d <= self.contact) & pair
        if self._below is None:
            self._below, self._touch = np.zeros_like(below), np.zeros_like(touch)
        self.below += int((below & ~self._below).sum()) // 2
        self.touching += int((touch & ~self._touch).sum()) // 2
        self._below, self._touch = below, touch
        if pair.any():
            self.closest = min(self.closest, float(d[pair].min()))
        self.samples += 1
