"""``swarm-train plot`` and training.plots: the episode is recorded faithfully and drawn with the promised parts."""
from __future__ import annotations

from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from matplotlib.colors import to_rgb

from runtime.spec import Role
from training.baselines import make_policy
from training.config import ExperimentConfig
from training.plots import ROLE_COLORS, record_episode, render_rgb, voronoi_polygons
from training.voronoi import bounded_cell_areas

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def role_based():
    return ExperimentConfig.from_toml(ROOT / "configs/role_based.toml")


@pytest.fixture(scope="module")
def trace(role_based):
    return record_episode(role_based, make_policy("classical", seed=2), seed=2)


def _has_color(img: np.ndarray, hex_color: str, tol: float = 0.03, min_px: int = 20) -> bool:
    c = np.array(to_rgb(hex_color))
    return int((np.abs(img[..., :3] - c).max(-1) < tol).sum()) >= min_px


def test_plot_command_writes_a_png_with_every_role_color(tmp_path, capsys, monkeypatch):
    from training.cli import main
    monkeypatch.chdir(ROOT)
    out = tmp_path / "figs" / "episode.png"
    assert main(["plot", "--config", "configs/role_based.toml", "--policy", "classical", "--seed", "1",
                 "--out", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = mpimg.imread(out)
    assert img.shape[0] > 400 and img.shape[1] > 400
    for role in (Role.PURSUER, Role.SCOUT, Role.EVADER):  # pursuers red, scouts blue, targets green
        assert _has_color(img, ROLE_COLORS[role]), role


def test_plot_command_bad_config_is_a_clear_error(tmp_path, capsys):
    from training.cli import main
    assert main(["plot", "--config", str(tmp_path / "none.toml"), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("swarm-train plot: error:") and "does not exist" in err
    assert not (tmp_path / "x.png").exists()
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["plot", "--config", str(ROOT / "configs/role_based.toml"), "--out", str(blocker / "x.png")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("swarm-train plot: error: --out: cannot write") and "Traceback" not in err


def test_recorded_episode_stays_in_the_free_arena(role_based, trace):
    spec = role_based.spec
    assert trace.pos.shape == (spec.timing.episode_steps + 1, spec.n_agents, 2)
    hw = spec.arena.half_width
    radius = np.asarray(spec.per_agent("radius"))
    assert (np.abs(trace.pos) <= hw - radius[:, None] + 1e-9).all()
    d = np.linalg.norm(trace.pos[:, :, None, :] - trace.obstacle_pos[None, None], axis=-1)
    assert (d >= trace.obstacle_radius[None, None] + radius[None, :, None] - 1e-9).all()
    # moves at most max_speed * control_period per step (the last frame is the episode's end, not a reset)
    step = np.linalg.norm(np.diff(trace.pos, axis=0), axis=-1)
    vmax = np.asarray(spec.per_agent("max_speed")) * spec.timing.control_period
    assert (step <= vmax[None] + 1e-9).all()
    assert trace.record is not None and 0 <= trace.record.coverage <= 1


def test_drawn_voronoi_cells_match_the_batched_kernel(trace):
    hw = trace.spec.arena.half_width
    for pts in (trace.pos[-1], trace.pos[0], np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]])):
        polys = voronoi_polygons(pts, hw)
        areas = [0.5 * abs(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(np.roll(p[:, 0], -1), p[:, 1]))
                 if len(p) >= 3 else 0.0 for p in polys]
        ref = bounded_cell_areas(pts[None], hw)[0]
        # coincident points: the drawing gives each the whole shared cell, the kernel splits it
        dup = np.array([sum(np.array_equal(p, q) for q in pts) for p in pts])
        np.testing.assert_allclose(np.array(areas) / dup, ref, atol=1e-9)


def test_render_rgb_up_to_a_step(trace):
    img = render_rgb(trace, step=10, size_px=200)
    assert img.shape == (200, 200, 3) and img.dtype == np.uint8
    assert _has_color(img / 255.0, ROLE_COLORS[Role.PURSUER], tol=0.05, min_px=5)
