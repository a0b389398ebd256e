"""The Crazyflie memory budget (issue 17): the figures measured in the real firmware, the export's refusal of a
placement that cannot fit, the template's Makefile under ``make -C``, and the firmware check script's input checks.
No network and no firmware tree needed: the firmware build itself is recorded in results/c_export_report.md."""
from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from firmware_export import cmsis_tables, fw_budget
from firmware_export.c_export import TEMPLATE_DIR
from firmware_export.mlp_graph import CExportError

ROOT = Path(__file__).resolve().parent.parent
REPORT = ROOT / "results" / "c_export_report.md"
SCRIPT = ROOT / "firmware_export" / "check_in_firmware.sh"
MODELS = ROOT / "models"


def _report_rows() -> dict[str, list[str]]:
    """The report's "In the real firmware" table: first cell -> cells."""
    text = REPORT.read_text()
    section = text[text.index("## In the real firmware"):]
    rows = {}
    for line in section.splitlines():
        if line.startswith("| ") and not line.startswith("| ---"):
            cells = [c.strip().strip("*") for c in line.strip("|").split("|")]
            rows[cells[0]] = cells
    return rows


def _bytes(cell: str) -> int:
    return int(cell.split()[0].replace(",", ""))


def test_budget_is_the_recorded_firmware_measurement():
    text = REPORT.read_text()
    assert fw_budget.FIRMWARE_COMMIT in text and fw_budget.FIRMWARE_CONFIG in text
    rows = _report_rows()
    stock = rows["stock firmware (no app)"]
    assert (_bytes(stock[3]), _bytes(stock[4]), _bytes(stock[5])) == (
        fw_budget.STOCK.flash, fw_budget.STOCK.ram, fw_budget.STOCK.ccm)
    # every recorded build with the app is what the budget predicts from the policy's tables and code
    measured = 0
    for label, (quant, weights_in, tables, code) in fw_budget.MEASURED_BUILDS.items():
        cells = rows[label]
        got = fw_budget.Usage(_bytes(cells[3]), _bytes(cells[4]), _bytes(cells[5]))
        want = fw_budget.predicted(tables, weights_in, code)
        assert (got.ram, got.ccm) == (want.ram, want.ccm), label
        assert 0 <= got.flash - want.flash <= fw_budget.ALIGN_SLACK, label
        assert cells[1] == quant and cells[2].startswith(weights_in), label
        assert code <= fw_budget.POLICY_CODE_MAX
        measured += 1
    assert measured >= 3
    assert fw_budget.predicted(0, "flash", 0) - fw_budget.STOCK == fw_budget.APP_SHELL


@pytest.mark.parametrize("quant, table_bytes", [("float", 28_936), ("int8w", 8_712)])
def test_default_placement_fits_the_stock_firmware_and_ccm_does_not(quant, table_bytes):
    """The 64-64 pursuer's tables (their sizes are asserted on the generated C in tests/test_c_export.py)."""
    need = fw_budget.check(table_bytes, "ram")
    for region in ("flash", "ram", "ccm"):
        assert getattr(need, region) <= getattr(fw_budget.CAPACITY, region)
    fw_budget.check(table_bytes, "flash")
    with pytest.raises(CExportError, match=r"--weights-in ccm: .* CCM.*use --weights-in ram"):
        fw_budget.check(table_bytes, "ccm")
    # the stock firmware leaves about 0.5 KB of CCM: nothing of this size fits there
    assert fw_budget.CAPACITY.ccm - (fw_budget.STOCK + fw_budget.APP_SHELL).ccm < 1024


def test_a_policy_too_large_for_sram_is_refused_with_the_int8_fix():
    free = fw_budget.CAPACITY.ram - (fw_budget.STOCK + fw_budget.APP_SHELL).ram
    with pytest.raises(CExportError, match=r"RAM.*--quant int8w"):
        fw_budget.check(free + 4, "ram")
    fw_budget.check(free, "ram")


def test_cli_refuses_ccm_in_one_line_and_writes_nothing(tmp_path, capsys):
    from firmware_export.cli import main

    out = tmp_path / "c"
    model = MODELS / "role_based" / "pursuer_0.onnx"
    assert main(["c", "--model", str(model), "--out", str(out), "--weights-in", "ccm"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--weights-in ram" in err and "Traceback" not in err
    assert not (out / "policy.c").exists()
    assert main(["c", "--model", str(model), "--out", str(out), "--weights-in", "ccm", "--ignore-budget"]) == 0
    assert (out / "policy.c").is_file()


def test_template_makefile_finds_its_folder_under_make_c(tmp_path):
    """`make -C APP` keeps the shell's PWD; the template must hand the firmware its own folder (CURDIR)."""
    make = shutil.which("make")
    if make is None:
        pytest.skip("make not installed")
    app = tmp_path / "app"
    shutil.copytree(TEMPLATE_DIR, app)
    fake = tmp_path / "fw" / "tools" / "make"
    fake.mkdir(parents=True)
    # the firmware's oot.mk defaults OOT to $(PWD) (crazyflie-firmware tools/make/oot.mk); print what it gets
    (fake / "oot.mk").write_text("OOT ?= $(PWD)\nOOT_CONFIG ?= $(OOT)/oot-config\n"
                                 "all:\n\t@echo OOT=$(OOT) CONFIG=$(OOT_CONFIG) CFLAGS=$(EXTRA_CFLAGS)\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = subprocess.run([make, "-s", "-C", str(app), f"CRAZYFLIE_BASE={tmp_path / 'fw'}"], cwd=elsewhere,
                         capture_output=True, text=True, timeout=60, check=True).stdout
    assert f"OOT={app} " in out and f"CONFIG={app}/app-config" in out and f"-I{app}/src" in out
    kbuild = (TEMPLATE_DIR / "src" / "Kbuild").read_text()
    assert re.search(r"CFLAGS_policy\.o \+= -O2 -ffast-math", kbuild)  # built as the emulator measured it


def test_check_script_names_what_is_missing(tmp_path):
    bash = shutil.which("bash")
    if bash is None:
        pytest.skip("bash not installed")
    r = subprocess.run([bash, str(SCRIPT), str(tmp_path / "nope")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "pass the firmware checkout" in r.stderr
    (tmp_path / "fw" / "tools" / "make").mkdir(parents=True)
    (tmp_path / "fw" / "tools" / "make" / "oot.mk").write_text("")
    r = subprocess.run([bash, str(SCRIPT), str(tmp_path / "fw")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "submodule update --init --recursive" in r.stderr
    r = subprocess.run([bash, str(SCRIPT)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "usage" in r.stderr


def test_generated_cmsis_sine_table(tmp_path):
    table = cmsis_tables.sin_table_f32()
    assert table.shape == (cmsis_tables.FAST_MATH_TABLE_SIZE + 1,) and table.dtype == np.float32
    np.testing.assert_allclose(table, np.sin(np.linspace(0, 2 * np.pi, 513)), atol=1e-7)
    text = cmsis_tables.tables_text()
    values = re.findall(r"(-?[0-9.]+(?:e-?[0-9]+)?)f", text.split("{", 1)[1])
    assert np.array_equal(np.array(values, dtype=np.float32), table)  # every literal reads back exactly
    out = tmp_path / "arm_common_tables.c"
    assert cmsis_tables.main([str(out)]) == 0 and out.read_text() == text
