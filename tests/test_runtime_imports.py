"""``runtime`` and ``groundstation`` never import torch or ``training`` (a drone's runtime needs numpy and
onnxruntime only; the ground station adds cflib and pymavlink): every module of both packages, found by walking
them, is imported in a fresh interpreter, and ``sys.modules`` is checked afterwards."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("runtime", "groundstation")
FORBIDDEN = ("torch", "training")
OPTIONAL = ("cflib", "pymavlink")
"""Optional extras (``swarmpursuit[crazyflie]``, ``[mavlink]``): a module that needs a missing one is not imported."""

CHILD = f"""
import importlib, json, pkgutil, sys

def fail(name):
    raise  # walk_packages calls this while the error of importing package `name` is being handled

imported, optional = [], []
for pkg in {PACKAGES!r}:
    top = importlib.import_module(pkg)
    for name in [pkg] + [m.name for m in pkgutil.walk_packages(top.__path__, pkg + ".", onerror=fail)]:
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if (exc.name or "").split(".")[0] not in {OPTIONAL!r}:
                raise
            optional.append(name)
        else:
            imported.append(name)
from runtime.cli import build_parser as runtime_parser
from groundstation.cli import build_parser as gs_parser
runtime_parser(); gs_parser()
bad = sorted(m for m in sys.modules if m.split(".")[0] in {FORBIDDEN!r})
print(json.dumps({{"imported": imported, "optional": optional, "forbidden": bad}}))
"""


def _modules_on_disk() -> set[str]:
    names = set()
    for pkg in PACKAGES:
        for f in (ROOT / pkg).rglob("*.py"):
            parts = f.relative_to(ROOT).with_suffix("").parts
            names.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def test_runtime_and_groundstation_modules_never_import_torch_or_training():
    out = subprocess.run([sys.executable, "-c", CHILD], cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-3000:]
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    walked = set(doc["imported"]) | set(doc["optional"])
    on_disk = _modules_on_disk()
    assert walked == on_disk, f"walked but not on disk: {sorted(walked - on_disk)}; missed: {sorted(on_disk - walked)}"
    assert "groundstation.sim.crazyflie" in doc["imported"] and "runtime.policy" in doc["imported"]
    assert doc["forbidden"] == [], (f"{', '.join(doc['forbidden'][:10])} imported by runtime/groundstation "
                                    f"(modules imported: {len(doc['imported'])}; needing a missing optional "
                                    f"extra: {doc['optional']})")
