"""Importing the runtime never imports torch (a drone's runtime needs numpy and onnxruntime only)."""
from __future__ import annotations

import subprocess
import sys

MODULES = ["runtime", "runtime.spec", "runtime.world", "runtime.observation", "runtime.metrics", "runtime.policy",
           "runtime.comms", "runtime.agent", "runtime.swarm", "runtime.cli"]


def test_runtime_modules_never_import_torch():
    code = ("import sys\n"
            + "".join(f"import {m}\n" for m in MODULES)
            + "from runtime.cli import build_parser; build_parser()\n"
            + "bad = sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.'))\n"
            + "print(','.join(bad))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"torch imported by the runtime: {out.stdout.strip()[:200]}"
