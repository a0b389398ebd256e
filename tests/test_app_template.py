"""The Crazyflie app template's build documentation stays true to the template and the CLI.

(The app itself is compiled for the Cortex-M4 and run on the host in tests/test_c_export.py.)"""
from __future__ import annotations

import re
import shlex

from firmware_export.c_export import TEMPLATE_DIR
from firmware_export.cli import build_parser

README = TEMPLATE_DIR / "README.md"


def _code_lines(text: str) -> list[str]:
    blocks = re.findall(r"```\n(.*?)```", text, flags=re.S)
    return [ln.split("#")[0].strip() for b in blocks for ln in b.splitlines() if ln.split("#")[0].strip()]


def test_readme_commands_parse_with_the_real_cli():
    cmds = [ln for ln in _code_lines(README.read_text()) if ln.startswith("swarm-export ")]
    assert {shlex.split(c)[1] for c in cmds} == {"onnx", "c"}
    parser = build_parser()
    for c in cmds:
        args = parser.parse_args(shlex.split(c)[1:])
        if args.command == "c":
            assert args.app is not None  # the README's export writes the app


def test_readme_build_uses_the_makefile_variable_and_oot_convention():
    text = README.read_text()
    makefile = (TEMPLATE_DIR / "Makefile").read_text()
    assert "CRAZYFLIE_BASE ?=" in makefile and "tools/make/oot.mk" in makefile
    makes = [ln for ln in _code_lines(text) if ln.startswith("make ")]
    assert makes and all("CRAZYFLIE_BASE=" in m for m in makes)
    assert any(m.endswith("cload") for m in makes)
    for name in ("Makefile", "Kbuild", "src/Kbuild", "app-config", "src/swarm_app.c", "src/swarm_logic.c"):
        assert (TEMPLATE_DIR / name).is_file() and name.split("/")[-1] in text, name


def test_readme_documents_every_param_and_log_of_the_app():
    src = (TEMPLATE_DIR / "src" / "swarm_app.c").read_text()
    text = README.read_text()
    params = re.findall(r"PARAM_ADD\(\w+, (\w+),", src)
    logs = re.findall(r"LOG_ADD\(\w+, (\w+),", src)
    assert "agent" in params and "heartbeat" in params and "inferUs" in logs
    for p in params:
        if re.fullmatch(r"ob\d[xyr]", p):
            continue  # documented as swarm.ob<k>x/y/r
        assert f"swarm.{p}" in text, p
    assert "swarm.ob<k>x" in text
    for name in logs:
        assert f"`{name}`" in text, name
    # the documented timings are the code's
    logic_h = (TEMPLATE_DIR / "src" / "swarm_logic.h").read_text()
    deadman = int(re.search(r"#define SWARM_DEADMAN_MS (\d+)u", logic_h).group(1))
    brake = int(re.search(r"#define SWARM_BRAKE_MS (\d+)u", src).group(1))
    assert f"{deadman} ms" in text and f"for {brake // 1000} s" in text
