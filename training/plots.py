"""Figures: one episode drawn from above (matplotlib, Agg backend, PNG files).

``record_episode`` runs one episode of a policy and keeps the trajectories; ``plot_episode`` draws it: the
arena, obstacles, pursuers red, scouts blue, targets green, trails, sensing disks and the bounded Voronoi
cells (every agent a seed) at the final step, over the area the pursuer team covered during the episode.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Circle, Polygon, Rectangle  # noqa: E402

from runtime.metrics import EpisodeRecord, MetricsAccumulator  # noqa: E402
from runtime.spec import Role, SwarmSpec  # noqa: E402
from training.voronoi import bounded_cell_polygons  # noqa: E402

log = logging.getLogger(__name__)

ROLE_COLORS = {Role.PURSUER: "#d62728", Role.SCOUT: "#1f77b4", Role.EVADER: "#2ca02c"}
"""Pursuers red, scouts blue, targets green."""
COVERED_COLOR = "#fbe3b4"
"""Shade of the free area the pursuer team has had within sensing range."""


@dataclass
class EpisodeTrace:
    """One recorded episode (env 0 of a batch of one)."""

    spec: SwarmSpec
    pos: np.ndarray
    """[T + 1, N, 2] positions [m], the start included."""
    obstacle_pos: np.ndarray
    """[K, 2] obstacle centres [m]."""
    obstacle_radius: np.ndarray
    """[K] obstacle radii [m]."""
    record: EpisodeRecord | None = None
    """The episode's metrics, when the env tracked them."""


def record_episode(cfg, policy, seed: int = 0) -> EpisodeTrace:
    """Runs one episode of ``policy`` in ``cfg``'s world (one env seeded like evaluation round 0 of ``seed``,
    see ``training.evaluate``) and returns its trace."""
    from training.env import PursuitEnv
    from training.evaluate import eval_seed

    spec = cfg.spec
    env = PursuitEnv(spec, cfg.rewards, n_envs=1, seed=eval_seed(seed, 0), track_metrics=True)
    obs = env.reset()
    s = env.state
    obstacle_pos, obstacle_radius = s.obstacle_pos[0].copy(), s.obstacle_radius[0].copy()
    frames = [s.pos[0].copy()]
    # every layout starts with self_pos, which holds the exact position even in the final observation
    # (the env has already reset the world when it reports the episode's end)
    sl = spec.layout(Role.PURSUER)["self_pos"].slice
    assert sl == spec.layout(Role.EVADER)["self_pos"].slice
    for _ in range(spec.timing.episode_steps):
        obs, _, done, info = env.step(policy.act(obs, env))
        frames.append(info["final_obs"][0, :, sl].copy() if done[0] else env.state.pos[0].copy())
    record = info["episodes"][0] if info.get("episodes") else None
    return EpisodeTrace(spec, np.stack(frames), obstacle_pos, obstacle_radius, record)


def voronoi_polygons(points: np.ndarray, half_width: float) -> list[np.ndarray]:
    """Each point's Voronoi cell clipped to ``[-half_width, half_width]^2``, as ``[V, 2]`` CCW vertices
    (possibly empty): the cells of the scouts' reward themselves (``training.voronoi.bounded_cell_polygons``)."""
    return bounded_cell_polygons(points, half_width)


def covered_cells(trace: EpisodeTrace) -> tuple[np.ndarray, np.ndarray]:
    """Raster ``[H, W]`` (row = y) of free cells the pursuer team had within sensing range, and the free mask,
    measured exactly as ``runtime.metrics`` does."""
    acc = MetricsAccumulator(trace.spec, 1)
    acc.begin_episodes(np.array([0]), trace.obstacle_pos[None], trace.obstacle_radius[None])
    n = trace.spec.n_agents
    none = np.zeros((1, n, n), dtype=bool)
    for pos in trace.pos[1:]:
        acc.update(pos[None], none)
    return acc.visited[0] & acc.free[0], acc.free[0]


def draw_episode(ax, trace: EpisodeTrace, step: int = -1, cells: bool = True, coverage: bool = True) -> None:
    """Draws ``trace`` up to ``step`` (default: the end) on ``ax``."""
    spec = trace.spec
    hw = spec.arena.half_width
    r_sense = spec.sensing.sensing_range
    pos = trace.pos[: (len(trace.pos) if step == -1 else step + 1)]
    final = pos[-1]
    if coverage and len(pos) > 1:
        seen, free = covered_cells(EpisodeTrace(spec, pos, trace.obstacle_pos, trace.obstacle_radius))
        img = np.where(seen, 1.0, np.nan)
        ax.imshow(img, extent=(-hw, hw, -hw, hw), origin="lower", cmap=ListedColormap([COVERED_COLOR]),
                  interpolation="nearest", zorder=0)
        ax.add_patch(Rectangle((0, 0), 0, 0, fc=COVERED_COLOR, label="covered"))
    ax.add_patch(Rectangle((-hw, -hw), 2 * hw, 2 * hw, fill=False, lw=1.5, ec="black", zorder=1))
    if cells:
        for poly in voronoi_polygons(final, hw):
            if len(poly) >= 3:
                ax.add_patch(Polygon(poly, closed=True, fill=False, ec="0.45", lw=0.6, ls="--", zorder=2))
    for c, r in zip(trace.obstacle_pos, trace.obstacle_radius):
        ax.add_patch(Circle(c, r, fc="0.35", ec="0.15", zorder=3))
    ax.plot([], [], "o", color="0.35", ms=9, label="obstacles")
    radius = spec.per_agent("radius")
    labelled: set[Role] = set()
    for i, role in enumerate(spec.roles):
        color = ROLE_COLORS[role]
        ax.plot(pos[:, i, 0], pos[:, i, 1], "-", color=color, lw=0.9, alpha=0.55, zorder=4)
        ax.plot(*pos[0, i], "o", mfc="none", mec=color, ms=4, zorder=4)
        if role is not Role.EVADER:
            ax.add_patch(Circle(final[i], r_sense, fc=color, ec=color, alpha=0.08, lw=0.5, zorder=4))
        label = None if role in labelled else f"{role.label}s" if role is not Role.EVADER else "targets"
        labelled.add(role)
        ax.add_patch(Circle(final[i], radius[i], fc=color, ec="black", lw=0.5, zorder=5))
        ax.plot([], [], "o", color=color, label=label)
    ax.set_xlim(-hw - 0.1, hw + 0.1)
    ax.set_ylim(-hw - 0.1, hw + 0.1)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def plot_episode(trace: EpisodeTrace, out: str | Path, title: str | None = None) -> Path:
    """Draws the whole episode (trails from the hollow start markers, final positions filled, sensing disks
    and Voronoi cells at the final step, covered area shaded) and writes a PNG to ``out``."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 7.4), dpi=120)
    draw_episode(ax, trace)
    text = title or ""
    if trace.record is not None:
        r = trace.record
        text += (("\n" if text else "") + f"min/mean/max distance {r.min_dist:.2f}/{r.avg_dist:.2f}/"
                 f"{r.max_dist:.2f} m, tracking {r.tracking_rate:.2f}, coverage {r.coverage:.2f}")
    ax.set_title(text, fontsize=9)
    ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    log.info("wrote %s", out)
    return out


def render_rgb(trace: EpisodeTrace, step: int = -1, size_px: int = 480) -> np.ndarray:
    """The episode up to ``step`` as an ``[H, W, 3]`` uint8 image (PettingZoo's ``rgb_array``)."""
    dpi = 100
    fig, ax = plt.subplots(figsize=(size_px / dpi, size_px / dpi), dpi=dpi)
    draw_episode(ax, trace, step, cells=True, coverage=False)
    fig.tight_layout()
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return img
