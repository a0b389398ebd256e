"""Evidence for a C export: parity of the host-compiled C against onnxruntime on random and simulator-recorded
observations, and the Cortex-M4 cost (flash, RAM, executed instructions, estimated cycles)."""
from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_export import fw_budget, m4_emu
from firmware_export.c_export import CExport
from firmware_export.observations import (parity_observations, random_observations,  # noqa: F401 (re-exported)
                                          recorded_observations)
from firmware_export.toolchain import HostPolicy, build_host_library

HOST_FLAGS = ("-O2", "-ffast-math")


def onnx_actions(model_path: str | Path, obs: np.ndarray) -> np.ndarray:
    import onnxruntime as ort

    sess = ort.InferenceSession(str(model_path), providers=["CPUExecutionProvider"])
    name = sess.get_inputs()[0].name
    return sess.run(None, {name: np.ascontiguousarray(obs, dtype=np.float32)})[0]


def host_policy(export: CExport, work: Path) -> HostPolicy:
    lib = build_host_library([export.source], work / f"libswarm_policy_{export.quant}.so", HOST_FLAGS)
    return HostPolicy(lib, export.model.obs_dim, export.model.act_dim)


@dataclass(frozen=True)
class CostReport:
    n_obs: int
    host_max_abs_diff: float
    m4_sizes: m4_emu.SectionSizes
    m4_max_abs_diff: float
    m4_run: m4_emu.M4Run
    table_bytes: int

    @property
    def us(self) -> float:
        return m4_emu.micros(self.m4_run.cycles)

    @property
    def us_total(self) -> float:
        """With the flash wait states of the ART cache model (``m4_emu``)."""
        return m4_emu.micros(self.m4_run.total_cycles)


def cost_report(export: CExport, model_path: str | Path, n_obs: int = 10_000, n_m4: int = 20,
                seed: int = 0) -> CostReport:
    spec, role = export.model.spec, export.model.role
    obs = parity_observations(spec, role, n_obs, seed)
    ref = onnx_actions(model_path, obs)
    with tempfile.TemporaryDirectory(prefix="swarm_c_") as tmp:
        work = Path(tmp)
        host = host_policy(export, work).act_batch(obs)
        build = m4_emu.build(export.source, work / "m4")
        pick = np.linspace(0, n_obs - 1, n_m4).astype(int)
        m4_acts = np.array([m4_emu.run(build, obs[i], count=False).act for i in pick])
        counted = m4_emu.run(build, obs[pick[-1]])  # a recorded observation
    return CostReport(n_obs, float(np.abs(host - ref).max()), build.sizes, float(np.abs(m4_acts - ref[pick]).max()),
                      counted, export.sources.weight_bytes)


def format_report(export: CExport, r: CostReport) -> str:
    m, s, run = export.model, r.m4_sizes, r.m4_run
    st = run.stalls
    scheme = ", ".join(f"{q.weight.shape[1]}->{q.weight.shape[0]} {'int8' if q.is_int8 else 'float'}"
                       for q in export.qlayers)
    lines = [
        f"model {m.source}: agent {m.agent_id}, role {m.role.label}, spec {m.spec.hash}, "
        f"{' -> '.join([str(m.obs_dim)] + [str(d.n_out) for d in m.layers])}, weights {export.quant} ({scheme}), "
        f"tanh {export.tanh}, tables read from {export.weights_in}",
        f"parity vs onnxruntime, {r.n_obs} observations (half random in the spec's ranges, half recorded from the "
        f"simulator): host C max |diff| {r.host_max_abs_diff:.3g}; emulated Cortex-M4 build max |diff| "
        f"{r.m4_max_abs_diff:.3g} (on 20 of them)",
        "Cortex-M4 build (arm-none-eabi-gcc -O2 -ffast-math -mcpu=cortex-m4 -mfpu=fpv4-sp-d16 -mfloat-abi=hard):",
        f"  flash: code {s.text} B + tables {s.rodata} B = {s.text + s.rodata} B; "
        f"RAM: static {s.data + s.bss} B, stack {s.stack} B; CCM: {s.ccm} B",
        f"  in the stock Crazyflie firmware ({fw_budget.FIRMWARE_COMMIT[:8]}) with the app: "
        + "; ".join(f"{k} {v:,} of {getattr(fw_budget.CAPACITY, k):,} B" for k, v in
                    vars(fw_budget.predicted(export.sources.weight_bytes, export.weights_in, s.text)).items()),
        f"  executed instructions per inference: {run.instructions}",
        f"  cycles, zero wait states (TRM timing model): {run.cycles} = {r.us:.1f} us at 168 MHz",
        f"  flash wait states (ART model: 5 WS per miss, cold 64-line I-cache, 8-line D-cache): "
        f"{st.icache_misses} I-misses + {st.dcache_misses} D-misses = {st.cycles} cycles; "
        f"{st.flash_data_reads} data reads from flash, {st.ram_table_reads} from static SRAM, {st.ccm_data_reads} "
        "from CCM (SRAM and CCM: zero wait states)",
        f"  per inference with wait states: {run.total_cycles} cycles = {r.us_total:.1f} us at 168 MHz",
        f"  swarm_policy_init (once): {run.init_instructions} instructions, {run.init_cycles} cycles "
        f"= {m4_emu.micros(run.init_cycles):.1f} us",
        "  by class (instructions, cycles): " + "; ".join(f"{k} {n}/{c}" for k, (n, c) in run.by_class.items()),
    ]
    return "\n".join(lines)


def object_report(obj: Path, model_path: str | Path, n_obs: int = 20, seed: int = 0) -> str:
    """Run a policy object compiled elsewhere (the ``src/policy.o`` of a firmware build of the app) in the
    emulator: its actions against onnxruntime on ``n_obs`` parity observations, and one inference's cost."""
    from firmware_export.mlp_graph import read_actor

    model = read_actor(model_path)
    obs = parity_observations(model.spec, model.role, max(n_obs, 2), seed)
    with tempfile.TemporaryDirectory(prefix="swarm_fwobj_") as tmp:
        b = m4_emu.build_from_object(Path(obj), Path(tmp))
        acts = np.array([m4_emu.run(b, o, act_dim=model.act_dim, count=False).act for o in obs])
        run = m4_emu.run(b, obs[-1], act_dim=model.act_dim)
    diff = float(np.abs(acts - onnx_actions(model_path, obs)).max())
    return (f"{obj} (as the firmware linked it) in the emulator: max |diff| vs onnxruntime {diff:.3g} on {len(obs)} "
            f"observations; {run.instructions} instructions, {run.total_cycles} cycles with flash wait states = "
            f"{m4_emu.micros(run.total_cycles):.1f} us at 168 MHz")


@dataclass(frozen=True)
class ParityRow:
    """One actor's host C against onnxruntime on the parity observations (max over the two action components)."""

    agent: str
    max_abs_diff: float
    random_max: float
    """Over the uniformly drawn half."""
    recorded_max: float
    """Over the half recorded from the simulator."""
    p99: float
    """99th percentile over the observations."""


def parity_rows(models: str | Path, quant: str = "int8w", n_obs: int = 10_000, seed: int = 0,
                calib_obs: int | None = None) -> list[ParityRow]:
    """Every actor of a models folder exported with ``quant`` (default settings: GPTQ rounding on the default
    calibration observations, tables in RAM) and compared on ``n_obs`` parity observations (``seed``)."""
    from firmware_export.c_export import CALIB_OBS, export_c
    from runtime.policy import read_manifest

    manifest = read_manifest(models)
    obs_by_role: dict = {}
    rows = []
    with tempfile.TemporaryDirectory(prefix="swarm_parity_") as tmp:
        for entry in manifest.agents:
            work = Path(tmp) / entry.id
            ex = export_c(entry.file, work, quant=quant, calib_obs=calib_obs or CALIB_OBS, check_budget=False)
            role = ex.model.role
            if role not in obs_by_role:
                obs_by_role[role] = parity_observations(ex.model.spec, role, n_obs, seed)
            obs = obs_by_role[role]
            d = np.abs(host_policy(ex, work).act_batch(obs) - onnx_actions(entry.file, obs)).max(axis=1)
            half = n_obs - n_obs // 2  # the random half comes first (parity_observations)
            rows.append(ParityRow(entry.id, float(d.max()), float(d[:half].max()), float(d[half:].max()),
                                  float(np.percentile(d, 99))))
    return rows


def parity_table(folders: list[str | Path], quant: str = "int8w", n_obs: int = 10_000, seed: int = 0) -> str:
    """A Markdown table: per actor, for each models folder, max |C - onnxruntime| (random / recorded half), p99."""
    cols = [parity_rows(f, quant, n_obs, seed) for f in folders]
    head = "| actor | " + " | ".join(f"{Path(f).name} {quant}: max (random / recorded), p99" for f in folders) + " |"
    lines = [head, "|---|" + "---|" * len(folders)]
    for k, row in enumerate(cols[0]):
        cells = [f"{c[k].max_abs_diff:.4f} ({c[k].random_max:.4f} / {c[k].recorded_max:.4f}), {c[k].p99:.4f}"
                 for c in cols]
        lines.append(f"| {row.agent} | " + " | ".join(cells) + " |")
    worst = ", ".join(f"{Path(f).name} {max(r.max_abs_diff for r in c):.4f}" for f, c in zip(folders, cols))
    return "\n".join(lines + ["", f"Worst: {worst}."])


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(description="emulate a policy object built inside the Crazyflie firmware, or "
                                            "tabulate the C export's parity over every actor of models folders")
    p.add_argument("--object", type=Path, help="APP/src/policy.o of a firmware build of the app")
    p.add_argument("--model", type=Path, help="the ONNX actor it was exported from")
    p.add_argument("--models", type=Path, nargs="+", metavar="DIR",
                   help="instead: every actor of these models folders, exported with --quant, against onnxruntime")
    p.add_argument("--quant", default="int8w", choices=("float", "int8w"), help="with --models (default int8w)")
    p.add_argument("--obs", type=int, default=10_000, help="with --models: parity observations (default 10,000)")
    args = p.parse_args(argv)
    if args.models:
        print(parity_table(args.models, args.quant, args.obs))
        return 0
    if args.object is None or args.model is None:
        p.error("give --object and --model, or --models DIR [DIR ...]")
    print(object_report(args.object, args.model))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
