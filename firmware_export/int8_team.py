"""How a team flies on the int8w C's arithmetic: every pursuer and scout actor of a models folder exported with
``--quant int8w`` (default GPTQ rounding and calibration) and run through ``quantize.int8_forward`` (what the C
computes, within 1e-4: tests/test_c_export.py), against the folder's own float evaders, on the held-out
evaluation episodes, beside the same team in float on the same episodes::

    python -m firmware_export.int8_team --models models/role_based --episodes 200 --seed 0
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from firmware_export.c_export import CALIB_OBS, export_c
from firmware_export.mlp_graph import CExportError
from firmware_export.quantize import int8_forward
from runtime.policy import read_manifest

ROWS = (("mean_min_dist", "min dist [m]", "{:.4f}"), ("mean_avg_dist", "mean dist [m]", "{:.4f}"),
        ("mean_max_dist", "max dist [m]", "{:.4f}"), ("tracking_rate", "tracking", "{:.3f}"),
        ("coverage", "coverage", "{:.3f}"), ("collisions_per_episode", "collisions/ep", "{:.2f}"))


class Int8Team:
    """The pursuer-team actors of a models folder on the int8w arithmetic (evader rows are zero)."""

    def __init__(self, folder: str | Path, calib_obs: int = CALIB_OBS) -> None:
        manifest = read_manifest(folder)
        spec = manifest.spec
        if spec.avoidance.enabled:
            raise CExportError(f"{folder}: its spec applies the avoidance layer to every action, which this "
                               "evaluation does not: evaluate a spec without [spec.avoidance]")
        nt = spec.team.n_team
        self.layers: list[tuple[int, int, Any]] = []
        with tempfile.TemporaryDirectory(prefix="swarm_int8team_") as tmp:
            for i, entry in enumerate(manifest.agents[:nt]):
                ex = export_c(entry.file, Path(tmp) / entry.id, quant="int8w", calib_obs=calib_obs,
                              check_budget=False)
                self.layers.append((i, ex.model.obs_dim, ex.qlayers))

    def act(self, obs: np.ndarray, env: Any = None) -> np.ndarray:
        out = np.zeros(obs.shape[:2] + (2,))
        for i, dim, ql in self.layers:
            out[:, i] = int8_forward(ql, obs[:, i, :dim])
        return out


def compare(folder: str | Path, episodes: int = 200, seed: int = 0, n_envs: int = 50,
            calib_obs: int = CALIB_OBS, cfg: Any = None) -> dict[str, dict]:
    """The float team and the int8w team, each against the folder's float evaders, on the same episodes.
    ``cfg``: the ``training.config.ExperimentConfig`` to evaluate in (default: the one in the folder's manifest)."""
    from training.baselines import TeamPolicy
    from training.evaluate import evaluate
    from training.learned_eval import load_learned
    from training.maddpg import OnnxActorsPolicy

    if cfg is None:
        cfg, learned, _ = load_learned(models=folder)
    else:
        learned = OnnxActorsPolicy(str(folder), cfg.spec)
    return {"float": evaluate(cfg, learned, episodes, seed=seed, n_envs=n_envs, progress=False),
            "int8w": evaluate(cfg, TeamPolicy(Int8Team(folder, calib_obs), learned), episodes, seed=seed,
                              n_envs=n_envs, progress=False)}


def markdown(folder: str | Path, res: dict[str, dict], episodes: int, seed: int) -> str:
    lines = [f"`python -m firmware_export.int8_team --models {folder} --episodes {episodes} --seed {seed}`: the "
             "pursuer team in float and on the int8w C's arithmetic, both against the folder's float evaders",
             "", "| team | " + " | ".join(label for _, label, _ in ROWS) + " |", "|---|" + "---|" * len(ROWS)]
    for name, m in res.items():
        lines.append(f"| {name} | " + " | ".join(fmt.format(m[key]) for key, _, fmt in ROWS) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", required=True, type=Path, help="models folder written by swarm-export onnx")
    p.add_argument("--episodes", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--n-envs", type=int, default=50)
    a = p.parse_args(argv)
    print(markdown(a.models, compare(a.models, a.episodes, a.seed, a.n_envs), a.episodes, a.seed))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
