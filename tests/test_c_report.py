"""``swarm-export c --report`` (the figures of results/c_export_report.md): the report of a small actor has
every section, and its numbers are finite, consistent with each other and plausible for a Cortex-M4."""
from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from firmware_export import fw_budget, m4_emu
from firmware_export.cli import main
from firmware_export.toolchain import arm_gcc
from runtime.spec import Role, SwarmSpec

pytestmark = pytest.mark.skipif(
    arm_gcc() is None or not any(shutil.which(cc) for cc in ("cc", "gcc", "clang")),
    reason="--report needs a host C compiler (cc, gcc or clang) and arm-none-eabi-gcc "
           "(apt-get install gcc gcc-arm-none-eabi libnewlib-arm-none-eabi)")

HIDDEN = (32, 32)
N_OBS = 1000
NUMBER = re.compile(r"\b(?:\d[\d,]*(?:\.\d+)?(?:e[-+]?\d+)?|nan|inf)\b", re.IGNORECASE)


def _actor_onnx(path: Path, spec: SwarmSpec, role: Role, seed: int) -> tuple[Path, int]:
    """A relu-relu-tanh MLP of MatMul+Add layers as ``swarm-export onnx`` writes one (metadata included), from
    seeded random weights; returns the path and the number of multiply-accumulates of one inference."""
    rng = np.random.default_rng(seed)
    dims = [spec.obs_dim(role), *HIDDEN, spec.act_dim]
    nodes, inits, cur = [], [], "obs"
    for i, (a, b) in enumerate(zip(dims, dims[1:])):
        inits += [numpy_helper.from_array(rng.normal(0, 1.5 / np.sqrt(a), (a, b)).astype(np.float32), f"w{i}"),
                  numpy_helper.from_array(rng.normal(0, 0.2, b).astype(np.float32), f"b{i}")]
        act = "Tanh" if i == len(dims) - 2 else "Relu"
        nodes += [helper.make_node("MatMul", [cur, f"w{i}"], [f"m{i}"]),
                  helper.make_node("Add", [f"m{i}", f"b{i}"], [f"z{i}"]),
                  helper.make_node(act, [f"z{i}"], [f"h{i}"])]
        cur = f"h{i}"
    nodes.append(helper.make_node("Identity", [cur], ["action"]))
    graph = helper.make_graph(nodes, "actor", [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", dims[0]])],
                              [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", dims[-1]])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    meta = {"spec_hash": spec.hash, "role": role.label, "agent_id": f"{role.label}_0",
            "spec_json": json.dumps(spec.to_dict()), "obs_dim": str(dims[0]), "act_dim": str(dims[-1])}
    for k, v in meta.items():
        p = model.metadata_props.add()
        p.key, p.value = k, v
    onnx.save(model, str(path))
    return path, sum(a * b for a, b in zip(dims, dims[1:]))


def _num(s: str) -> float:
    return float(s.replace(",", ""))


def _field(pattern: str, text: str) -> tuple[float, ...]:
    m = re.search(pattern, text)
    assert m, f"the report has no line matching {pattern!r}:\n{text}"
    return tuple(_num(g) for g in m.groups())


@pytest.mark.parametrize("quant, tol", [("float", 1e-5), ("int8w", 0.06)])
def test_c_report_sections_and_figures(tmp_path, capsys, quant, tol):
    spec = SwarmSpec()
    model, macs = _actor_onnx(tmp_path / "pursuer_0.onnx", spec, Role.PURSUER, seed=7)
    rc = main(["c", "--model", str(model), "--out", str(tmp_path / "c"), "--quant", quant, "--calib-obs", "2000",
               "--report", "--report-obs", str(N_OBS)])
    out, err = capsys.readouterr()
    assert rc == 0, err
    lines = out.strip().splitlines()
    wrote, report = lines[0], "\n".join(lines[1:])
    for needle in ("model ", "parity vs onnxruntime", "Cortex-M4 build (", "  flash: code ",
                   "  in the stock Crazyflie firmware (", "  executed instructions per inference: ",
                   "  cycles, zero wait states", "  flash wait states (ART model", "  per inference with wait states: ",
                   "  swarm_policy_init (once): ", "  by class (instructions, cycles): "):
        assert sum(line.startswith(needle) for line in lines[1:]) == 1, f"{needle!r} is not one line of:\n{report}"
    numbers = [_num(n) for n in NUMBER.findall("\n".join(lines[2:]))]  # after the model's line (its path)
    assert numbers and all(math.isfinite(n) for n in numbers), report

    head = lines[1]
    dims = " -> ".join(map(str, [spec.obs_dim(Role.PURSUER), *HIDDEN, spec.act_dim]))
    assert f"agent pursuer_0, role pursuer, spec {spec.hash}, {dims}, weights {quant} (" in head
    assert head.endswith("tanh fast, tables read from ram")
    (tables,) = _field(r"weights \S+ \(([\d,]+) B of tables", wrote)
    # parity: the host build and the emulated M4 build compute what onnxruntime computes
    host_diff, m4_diff = _field(rf"{N_OBS} observations .*host C max \|diff\| (\S+); emulated Cortex-M4 build "
                                r"max \|diff\| (\S+) \(on 20 of them\)", report)
    assert 0 <= host_diff <= tol and 0 <= m4_diff <= tol
    # sizes: the tables are in flash (the copy's source) and copied to static RAM (the default placement)
    code, rodata, flash, static, stack, ccm = _field(r"flash: code (\d+) B \+ tables (\d+) B = (\d+) B; RAM: static "
                                                     r"(\d+) B, stack (\d+) B; CCM: (\d+) B", report)
    assert 200 < code <= fw_budget.POLICY_CODE_MAX and rodata >= tables and flash == code + rodata
    assert static == tables and 0 < stack <= 1024 and ccm == 0
    if quant == "float":
        assert tables == 4 * (macs + sum(HIDDEN) + spec.act_dim)
    else:  # int8 hidden layers: about a byte per weight instead of four
        assert tables < 0.5 * 4 * macs
    fw = re.search(r"with the app: flash ([\d,]+) of ([\d,]+) B; ram ([\d,]+) of ([\d,]+) B; ccm ([\d,]+) of "
                   r"([\d,]+) B", report)
    assert fw, report
    used = [_num(g) for g in fw.groups()]
    for u, cap, stock in zip(used[::2], used[1::2], (fw_budget.STOCK.flash, fw_budget.STOCK.ram, fw_budget.STOCK.ccm)):
        assert stock < u <= cap
    # cost: the trace saw the whole inference, and the cycle figures add up
    (instr,) = _field(r"executed instructions per inference: (\d+)", report)
    cycles, us = _field(r"zero wait states \(TRM timing model\): (\d+) = (\S+) us at 168 MHz", report)
    i_miss, d_miss, stall = _field(r"(\d+) I-misses \+ (\d+) D-misses = (\d+) cycles", report)
    total, us_total = _field(r"per inference with wait states: (\d+) cycles = (\S+) us at 168 MHz", report)
    init_instr, init_cycles, init_us = _field(r"swarm_policy_init \(once\): (\d+) instructions, (\d+) cycles "
                                              r"= (\S+) us", report)
    assert instr > (macs // 4 if quant == "int8w" else macs // 2)  # SMLAD: two int8 MACs an instruction
    assert instr <= cycles <= 4 * instr and 0 < us < 200
    assert us == pytest.approx(m4_emu.micros(cycles), abs=0.06)
    assert stall == m4_emu.FLASH_WAIT_STATES * (i_miss + d_miss) and total == cycles + stall
    assert us_total == pytest.approx(m4_emu.micros(total), abs=0.06) and us_total >= us
    assert init_instr > 0 and init_cycles >= init_instr and init_us == pytest.approx(m4_emu.micros(init_cycles),
                                                                                        abs=0.06)
    by_class = re.search(r"by class \(instructions, cycles\): (.*)$", report, re.MULTILINE).group(1)
    per_class = [tuple(map(int, m)) for m in re.findall(r" (\d+)/(\d+)(?:;|$)", by_class)]
    assert per_class and sum(n for n, _ in per_class) == instr and sum(c for _, c in per_class) == cycles
