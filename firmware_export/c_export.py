"""``swarm-export c``: write ``policy.h`` and ``policy.c`` for one ONNX actor (the file-writing shell around
``cgen``), and the reference the generated C is checked against."""
from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_export import fw_budget
from firmware_export.cgen import DEFAULT_WEIGHTS_IN, CSources, generate
from firmware_export.mlp_graph import ActorModel, CExportError, Dense, read_actor
from firmware_export.observations import parity_observations
from firmware_export.quantize import QDense, dequantized, float_layers, quantize_layers

log = logging.getLogger(__name__)

TEMPLATE_DIR = Path(__file__).parent / "templates" / "crazyflie_app"
"""The Crazyflie out-of-tree app; ``install_app`` copies it and adds the generated policy to its ``src/``."""
STUBS_DIR = Path(__file__).parent / "fw_stubs"
"""Minimal stand-ins for the firmware headers (and a host implementation) so tests can build the app."""
CALIB_SEED = 1000
"""Seed of the int8 calibration observations; parity checks use other seeds (0 in ``c_report``), so the
quantization is measured on observations it never saw."""
CALIB_OBS = 20_000


def calibration_observations(model: ActorModel, n: int = CALIB_OBS, seed: int = CALIB_SEED) -> np.ndarray:
    """Half uniform in the spec's ranges, half recorded from the simulator, from seeds the parity checks do not use."""
    if n < 2:
        raise CExportError(f"--calib-obs {n}: use at least a few thousand calibration observations")
    return parity_observations(model.spec, model.role, n, seed, recorded_seed=seed + 1)


@dataclass(frozen=True)
class CExport:
    model: ActorModel
    sources: CSources
    header: Path
    source: Path
    quant: str
    tanh: str
    weights_in: str
    qlayers: tuple[QDense, ...]
    """The layers as the C computes them (int8 rows and scales for ``int8w``)."""


def export_c(model_path: str | Path, out_dir: str | Path, quant: str = "float", tanh: str = "fast",
             spec_toml: str | Path | None = None, role: str | None = None, weights_in: str = DEFAULT_WEIGHTS_IN,
             int8_rounding: str = "gptq", calib_obs: int = CALIB_OBS, check_budget: bool = True) -> CExport:
    """Write ``policy.h``/``policy.c``; with ``check_budget`` refuse (``CExportError``, naming the fix) tables that
    do not fit the memory the stock Crazyflie firmware leaves free (``firmware_export.fw_budget``)."""
    model = read_actor(model_path, spec_toml=spec_toml, role=role)
    if quant == "int8w":
        calib = calibration_observations(model, calib_obs) if int8_rounding == "gptq" else None
        qlayers = quantize_layers(model.layers, calib, int8_rounding)
    else:
        qlayers = float_layers(model.layers)
    sources = generate(model, quant=quant, tanh=tanh, weights_in=weights_in, qlayers=qlayers)
    if check_budget:
        fw_budget.check(sources.weight_bytes, weights_in, f"{model.agent_id} ({quant})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    header, source = out / "policy.h", out / "policy.c"
    from runtime.cliutil import write_text_atomic  # never a half-written C file after an error or Ctrl-C
    write_text_atomic(header, sources.header)
    write_text_atomic(source, sources.source)
    log.info("wrote %s and %s (%s, %d weight bytes, read from %s)", header, source, quant, sources.weight_bytes,
             weights_in)
    return CExport(model, sources, header, source, quant, tanh, weights_in, qlayers)


def install_app(export: CExport, app_dir: str | Path) -> Path:
    """Copy the Crazyflie app template to ``app_dir`` with this export's ``policy.h``/``policy.c`` in ``src/``."""
    dst = Path(app_dir)
    shutil.copytree(TEMPLATE_DIR, dst, dirs_exist_ok=True)
    shutil.copyfile(export.header, dst / "src" / "policy.h")
    shutil.copyfile(export.source, dst / "src" / "policy.c")
    log.info("wrote the Crazyflie app to %s", dst)
    return dst


def mlp_forward(layers: tuple[Dense, ...], obs: np.ndarray) -> np.ndarray:
    """float64 forward pass of ``layers`` on ``obs`` [B, in] (the reference for the quantized C)."""
    x = np.asarray(obs, dtype=np.float64)
    for d in layers:
        x = x @ d.weight.astype(np.float64).T + d.bias.astype(np.float64)
        if d.activation == "relu":
            x = np.maximum(x, 0.0)
        elif d.activation == "tanh":
            x = np.tanh(x)
    return x


def reference_layers(export: CExport) -> tuple[Dense, ...]:
    """The layers the generated C computes (dequantized for ``int8w``)."""
    return dequantized(export.qlayers)
