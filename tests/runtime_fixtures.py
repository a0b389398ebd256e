"""Exported models for the runtime tests: random-initialised actors of a spec, exported once per session.

Until trained models ship, the runtime is tested on actors with random weights; the export path is the real
one (``firmware_export.onnx_export.export_run``), parity checks included.
"""
from __future__ import annotations

import functools
import tempfile
from pathlib import Path

from runtime.spec import SwarmSpec

_ROOT = Path(tempfile.mkdtemp(prefix="swarm-runtime-tests-"))


def make_run(run_dir: Path, spec: SwarmSpec, seed: int = 0) -> Path:
    import torch

    from training.checkpoint import save_actors
    from training.networks import Actor
    torch.manual_seed(seed)
    save_actors(run_dir / "actors.pt", spec, [Actor(spec.obs_dim(r)) for r in spec.roles],
                config={"note": "random-initialised test actors"}, meta={"evaluation": {"tracking_rate": 0.5}})
    return run_dir


@functools.lru_cache(maxsize=4)
def exported(partial: bool = False) -> tuple[Path, Path, dict]:
    """(run folder, models folder, manifest) for the default spec (``partial``: partial observability)."""
    import torch

    from firmware_export.onnx_export import export_run
    spec = SwarmSpec.from_dict({"sensing": {"observability": "partial"}}) if partial else SwarmSpec()
    name = "partial" if partial else "full"
    # one torch thread, as tests/conftest.py gives every test that has torch imported already: the first call
    # imports torch itself, inside a fixture. With two threads on 2 busy cores the export's 3,600 small
    # forward passes took 48 s instead of 11 (load 3-4).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        run = make_run(_ROOT / "runs" / name, spec)
        models = _ROOT / "models" / name
        manifest = export_run(run, models)
    finally:
        torch.set_num_threads(threads)
    return run, models, manifest
