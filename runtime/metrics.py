"""The paper's metrics, shared by evaluation (thousands of envs) and flight (one).

Per control step and env:

- pursuer-target distances: every (pursuer, evader) pair's centre distance; the step's minimum, mean and
  maximum (the paper's three columns), averaged over steps and then episodes. Only agents with the pursuer
  role count (scouts explore); with no pursuers, scouts stand in.
- tracking rate: fraction of (step, evader) pairs with a pursuer within the sensing range.
- coverage: fraction of the arena's free area (obstacles excluded) that pursuers and scouts have had within
  their sensing range during the episode (``coverage``), and the same for the current step averaged over the
  episode (``coverage_instant``). Measured on a raster of ``resolution`` m cells, cell centres tested exactly
  against every agent's sensing disc.
- collisions: onsets of contact (distance <= R_i + R_j between two agents, or an agent touching an obstacle),
  split by whose fault they are: ``teammate_contacts`` (pursuer/scout with pursuer/scout),
  ``team_obstacle_contacts`` (a pursuer or scout touching an obstacle) and ``evader_contacts`` (evaders with
  each other or with an obstacle: the opponents' doing, not the team's). ``team_contacts`` is the team's share
  (teammate + team-obstacle) and ``collisions`` the total of all three, the figure reported before the split.
- captures: onsets of contact between a pursuer-team agent and an evader (never counted as a collision).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.spec import Role, SwarmSpec

METRIC_KEYS = ("episodes", "mean_min_dist", "mean_avg_dist", "mean_max_dist", "tracking_rate", "coverage",
               "coverage_instant", "collisions_per_episode", "team_contacts_per_episode",
               "teammate_contacts_per_episode", "team_obstacle_contacts_per_episode", "evader_contacts_per_episode",
               "captures_per_episode")
CONTACT_KINDS = ("teammate", "team_obstacle", "evader")
"""The three parts of ``collisions``, in the order of ``EpisodeRecord.contacts``."""


@dataclass
class EpisodeRecord:
    min_dist: float
    avg_dist: float
    max_dist: float
    tracking_rate: float
    coverage: float
    coverage_instant: float
    collisions: int
    """All contact onsets: teammate + team_obstacle + evader."""
    captures: int
    steps: int
    teammate: int = 0
    """Onsets of contact between two pursuer-team agents (pursuers and scouts)."""
    team_obstacle: int = 0
    """Onsets of a pursuer-team agent touching an obstacle."""
    evader: int = 0
    """Onsets of contact between two evaders or between an evader and an obstacle."""

    @property
    def team_contacts(self) -> int:
        """The pursuer team's own contacts: teammate + team_obstacle."""
        return self.teammate + self.team_obstacle


class MetricsAccumulator:
    """Accumulates the metrics of ``n_envs`` envs step by step; ``end_episodes`` closes finished ones."""

    def __init__(self, spec: SwarmSpec, n_envs: int, resolution: float = 0.05) -> None:
        self.spec = spec
        self.n_envs = n_envs
        t = spec.team
        self.nt = t.n_team
        self.pursuers = np.array(t.indices(Role.PURSUER)) if t.n_pursuers else np.array(t.indices(Role.SCOUT))
        self.radius = np.array(spec.per_agent("radius"))
        hw = spec.arena.half_width
        self.cells = int(math.ceil(2 * hw / resolution))
        self.res = 2 * hw / self.cells
        centres = -hw + (np.arange(self.cells) + 0.5) * self.res
        self.cx, self.cy = np.meshgrid(centres, centres, indexing="xy")  # [H, W], row = y
        half = int(math.ceil(spec.sensing.sensing_range / self.res)) + 1
        self.row_off = np.arange(-half, half + 1)
        # collision pairs: teammates with teammates, evaders with evaders; capture pairs: team x evaders
        n = spec.n_agents
        team = np.arange(n) < self.nt
        same = team[:, None] == team[None, :]
        iu = np.triu(np.ones((n, n), dtype=bool), 1)
        self.team_mask = team
        self.teammate_pairs = same & team[:, None] & iu
        self.evader_pairs = same & ~team[:, None] & iu
        self.collision_pairs = same & iu
        self.capture_pairs = ~same & iu
        self.visited = np.zeros((n_envs, self.cells, self.cells), dtype=bool)
        self.free = np.ones((n_envs, self.cells, self.cells), dtype=bool)
        self.free_count = np.ones(n_envs)
        self._prev_contact = np.zeros((n_envs, n, n), dtype=bool)
        self._prev_obstacle = np.zeros((n_envs, n), dtype=bool)
        self._sums = np.zeros((n_envs, 6))  # min, mean, max, tracked pairs, instant coverage, steps
        self._contacts = np.zeros((n_envs, len(CONTACT_KINDS)), dtype=np.int64)  # CONTACT_KINDS order
        self._captures = np.zeros(n_envs, dtype=np.int64)
        self.records: list[EpisodeRecord] = []

    def begin_episodes(self, env_ids: np.ndarray, obstacle_pos: np.ndarray, obstacle_radius: np.ndarray) -> None:
        """Start new episodes in ``env_ids`` with these obstacles (``[len(ids), K, 2]``, ``[len(ids), K]``)."""
        ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        if ids.size == 0:
            return
        free = np.ones((ids.size, self.cells, self.cells), dtype=bool)
        for k in range(obstacle_pos.shape[1]):
            dx = self.cx[None] - obstacle_pos[:, k, 0, None, None]
            dy = self.cy[None] - obstacle_pos[:, k, 1, None, None]
            free &= dx * dx + dy * dy > obstacle_radius[:, k, None, None] ** 2
        self.free[ids] = free
        self.free_count[ids] = free.reshape(ids.size, -1).sum(-1)
        self.visited[ids] = False
        self._prev_contact[ids] = False
        self._prev_obstacle[ids] = False
        self._sums[ids] = 0.0
        self._contacts[ids] = 0
        self._captures[ids] = 0

    def update(self, pos: np.ndarray, contacts: np.ndarray, obstacle_contacts: np.ndarray | None = None,
               dist: np.ndarray | None = None) -> None:
        """One step of every env: positions ``[B, N, 2]``, contacts ``[B, N, N]``, obstacle contacts ``[B, N]``."""
        b = pos.shape[0]
        nt = self.nt
        if dist is None:
            d = pos[:, :, None, :] - pos[:, None, :, :]
            dist = np.sqrt((d * d).sum(-1))
        pd = dist[:, self.pursuers][:, :, nt:]  # [B, P, E]
        flat = pd.reshape(b, -1)
        r = self.spec.sensing.sensing_range
        tracked = (pd.min(axis=1) <= r).mean(axis=1)
        inst = self._mark_coverage(pos[:, :nt])
        self._sums += np.stack([flat.min(1), flat.mean(1), flat.max(1), tracked, inst, np.ones(b)], axis=1)
        onset = contacts & ~self._prev_contact
        self._contacts[:, 0] += (onset & self.teammate_pairs[None]).sum((1, 2))
        self._contacts[:, 2] += (onset & self.evader_pairs[None]).sum((1, 2))
        self._captures += (onset & self.capture_pairs[None]).sum((1, 2))
        self._prev_contact = contacts.copy()
        if obstacle_contacts is not None:
            o = obstacle_contacts & ~self._prev_obstacle
            self._contacts[:, 1] += o[:, self.team_mask].sum(1)
            self._contacts[:, 2] += o[:, ~self.team_mask].sum(1)
            self._prev_obstacle = obstacle_contacts.copy()

    def _mark_coverage(self, pos: np.ndarray) -> np.ndarray:
        """Marks cells within sensing range of ``pos`` [B, M, 2] as visited; returns instant coverage [B].

        In each raster row the cells whose centres lie in an agent's disc form one run ``[x0, x1]``; each
        agent's runs are cut out of the square window of rows and columns around it and set by index (the same
        cells as testing every centre; ~2x faster than painting the runs with a difference array and a
        cumulative sum over the whole raster, which spent its time on the raster's full width)."""
        b = pos.shape[0]
        hw = self.spec.arena.half_width
        r = self.spec.sensing.sensing_range
        c, res = self.cells, self.res
        iy = np.floor((pos[..., 1] + hw) / res).astype(np.int64)
        ix = np.floor((pos[..., 0] + hw) / res).astype(np.int64)
        rows = iy[..., None] + self.row_off  # [B, M, R]
        dy = -hw + (rows + 0.5) * res - pos[..., 1, None]
        h2 = r * r - dy * dy
        h = np.sqrt(np.maximum(h2, 0.0))
        px = pos[..., 0, None]
        x0 = np.maximum(np.ceil((px - h + hw) / res - 0.5), 0).astype(np.int64)
        x1 = np.minimum(np.floor((px + h + hw) / res - 0.5), c - 1).astype(np.int64)
        ok = (h2 >= 0) & (rows >= 0) & (rows < c) & (x0 <= x1)
        # a run spans at most 2 r / res + 1 cells around the agent's own column: the window row_off covers it
        cols = (ix[..., None] + self.row_off)[..., None, :]  # [B, M, 1, W]
        inside = ok[..., None] & (cols >= x0[..., None]) & (cols <= x1[..., None])  # [B, M, R, W]
        idx = ((np.arange(b)[:, None, None, None] * c + rows[..., None]) * c + cols)[inside]
        now = np.zeros(b * c * c, dtype=bool)
        now[idx] = True
        now = now.reshape(b, c, c)
        now &= self.free[:b]
        self.visited[:b] |= now
        return now.reshape(b, -1).sum(-1) / self.free_count[:b]

    def end_episodes(self, env_ids: np.ndarray) -> list[EpisodeRecord]:
        """Close the episodes of ``env_ids`` and record them."""
        out = []
        for e in np.asarray(env_ids, dtype=np.int64).reshape(-1):
            steps = self._sums[e, 5]
            if steps == 0:
                continue
            m = self._sums[e] / steps
            cov = float((self.visited[e] & self.free[e]).sum() / self.free_count[e])
            tm, to, ev = (int(c) for c in self._contacts[e])
            rec = EpisodeRecord(float(m[0]), float(m[1]), float(m[2]), float(m[3]), cov, float(m[4]),
                                tm + to + ev, int(self._captures[e]), int(steps), tm, to, ev)
            out.append(rec)
        self.records += out
        return out

    def summary(self) -> dict[str, float]:
        return summarize(self.records)


def summarize(records: list[EpisodeRecord]) -> dict[str, float]:
    """The evaluator's JSON keys (``METRIC_KEYS``), averaged over episodes."""
    if not records:
        return {"episodes": 0}
    def avg(attr: str) -> float:
        return float(np.mean([getattr(r, attr) for r in records]))
    return {
        "episodes": len(records),
        "mean_min_dist": avg("min_dist"),
        "mean_avg_dist": avg("avg_dist"),
        "mean_max_dist": avg("max_dist"),
        "tracking_rate": avg("tracking_rate"),
        "coverage": avg("coverage"),
        "coverage_instant": avg("coverage_instant"),
        "collisions_per_episode": avg("collisions"),
        "team_contacts_per_episode": avg("team_contacts"),
        "teammate_contacts_per_episode": avg("teammate"),
        "team_obstacle_contacts_per_episode": avg("team_obstacle"),
        "evader_contacts_per_episode": avg("evader"),
        "captures_per_episode": avg("captures"),
    }
