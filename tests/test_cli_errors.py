"""Every bad input of every command ends in one line on stderr that names the option, the value and the fix,
exit status 2, no traceback and no output file: before any work starts (in-process, so the file stays fast)."""
from __future__ import annotations

import argparse
import importlib
import json
import math
from pathlib import Path

import pytest

from runtime import cliutil

ROOT = Path(__file__).resolve().parents[1]
MODELS = str(ROOT / "models" / "role_based")
ACTOR = str(ROOT / "models" / "role_based" / "pursuer_0.onnx")
CONFIG = str(ROOT / "configs" / "role_based.toml")


@pytest.fixture
def paths(tmp_path):
    """A file (``FILE``), a folder (``DIR``), a broken TOML (``BAD``) and a missing path (``NONE``)."""
    (tmp_path / "afile").write_text("x\n")
    (tmp_path / "adir").mkdir()
    (tmp_path / "bad.toml").write_text("not = [toml\n")
    return {"FILE": str(tmp_path / "afile"), "DIR": str(tmp_path / "adir"), "BAD": str(tmp_path / "bad.toml"),
            "NONE": str(tmp_path / "none"), "TMP": str(tmp_path)}


def _run(module: str, argv: list[str], capsys) -> tuple[int, str]:
    main = importlib.import_module(module).main
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse
        rc = exc.code
    return rc, capsys.readouterr().err


# (module, argv with FILE/DIR/BAD/NONE/TMP placeholders, what the line must contain, a path that must not exist)
CASES = [
    ("runtime.cli", "degrade --models M --losses ''", ["--losses", "''", "e.g. 0,0.2,0.5"], None),
    ("runtime.cli", "degrade --models M --losses 0,,1", ["--losses", "comma-separated"], None),
    ("runtime.cli", "degrade --models M --losses 0,2", ["--losses", "[0, 1]", "'0,2'"], None),
    ("runtime.cli", "degrade --models M --latencies -0.1", ["--latencies", ">= 0"], None),
    ("runtime.cli", "degrade --models M --baseline-repeats -1", ["--baseline-repeats", "'-1'", ">= 0"], None),
    ("runtime.cli", "degrade --models M --out FILE/x", ["--out", "is a file"], "FILE/x.md"),
    ("runtime.cli", "bench --models M --idle inf", ["--idle", "'inf'", "finite"], None),
    ("runtime.cli", "bench --models M --idle 0", ["--idle", "(0, 60]"], None),
    ("runtime.cli", "bench --models M --loop-seconds -1", ["--loop-seconds", "'-1'"], None),
    ("runtime.cli", "bench --models M --calls abc", ["--calls", "'abc'", "whole number"], None),
    ("runtime.cli", "bench --models M --agent -1", ["--agent", "'-1'"], None),
    ("runtime.cli", "bench --models M --json FILE/b.json", ["--json", "is a file"], "FILE/b.json"),
    ("runtime.cli", "run --models M --duration nan", ["--duration", "'nan'", "> 0"], None),
    ("runtime.cli", "run --models M --bandwidth nan", ["--bandwidth", "'nan'"], None),
    ("runtime.cli", "run --models M --jitter inf", ["--jitter", "'inf'"], None),
    ("runtime.cli", "run --models M --loss 1.5", ["--loss", "'1.5'", "[0, 1]"], None),
    ("runtime.cli", "run --models M --json FILE/r.json", ["--json", "is a file"], "FILE/r.json"),
    ("runtime.cli", "run --models M --json DIR", ["--json", "is a folder"], None),
    ("runtime.cli", "run --models NONE", ["ModelNotFound", "swarm-export onnx"], None),
    ("runtime.cli", "run --models DIR", ["manifest.json", "swarm-export onnx"], None),
    ("runtime.cli", "run --models M --seed -1", ["--seed", "'-1'", ">= 0"], None),
    ("runtime.cli", "run --models M --engine gpu", ["--engine", "'gpu'"], None),
    ("training.cli", "evaluate --json FILE/e.json --episodes 1", ["--json", "is a file"], "FILE/e.json"),
    ("training.cli", "evaluate --md FILE/e.md --episodes 1", ["--md", "is a file"], "FILE/e.md"),
    ("training.cli", "evaluate --plot DIR --episodes 1", ["--plot", "is a folder"], None),
    ("training.cli", "evaluate --episodes 0", ["--episodes", "'0'", ">= 1"], None),
    ("training.cli", "evaluate --n-envs x", ["--n-envs", "'x'"], None),
    ("training.cli", "evaluate --config BAD --episodes 1", ["not valid TOML", "BAD"], None),
    ("training.cli", "evaluate --config DIR --episodes 1", ["DIR"], None),
    ("training.cli", "evaluate --config NONE --episodes 1", ["does not exist"], None),
    ("training.cli", "plot --out FILE/p.png", ["--out", "is a file"], "FILE/p.png"),
    ("training.cli", "crossplay NONE --json FILE/c.json", ["--json", "is a file"], "FILE/c.json"),
    ("training.cli", "train --config C --out FILE/run", ["--out", "is a file"], "FILE/run"),
    ("training.cli", "train --config C --out FILE", ["--out", "is a file"], None),
    ("training.cli", "train --config C --out TMP/r --steps -5", ["--steps", "'-5'", ">= 1"], "TMP/r"),
    ("training.cli", "train --config C --out TMP/r --n-envs 0", ["--n-envs", "'0'"], "TMP/r"),
    ("training.cli", "train --config C --out TMP/r --threads 0", ["--threads", "'0'"], "TMP/r"),
    ("training.cli", "train --config C --out TMP/r --device tpu", ["train.device", "'tpu'"], "TMP/r"),
    ("training.cli", "train --config BAD --out TMP/r", ["not valid TOML"], "TMP/r"),
    ("training.cli", "train --config C --out TMP/r --init-from DIR", ["--init-from", "state.pt"], "TMP/r"),
    ("training.cli", "sweep --config BAD", ["not valid TOML"], None),
    ("training.cli", "sweep --steps 0", ["--steps", "'0'"], None),
    ("training.cli", "sweep --workers 0", ["--workers", "'0'"], None),
    ("training.cli", "sweep --json FILE/s.json --steps 1", ["--json", "is a file"], "FILE/s.json"),
    ("training.cli", "sweep --out FILE --steps 1", ["--out", "is a file"], None),
    ("firmware_export.cli", "c --model A --out FILE", ["--out", "is a file"], None),
    ("firmware_export.cli", "c --model A --out FILE/c", ["--out", "is a file"], "FILE/c"),
    ("firmware_export.cli", "c --model A --out TMP/c --report --report-obs 0", ["--report-obs", "'0'"], "TMP/c"),
    ("firmware_export.cli", "c --model A --out TMP/c --calib-obs -1", ["--calib-obs", "'-1'"], "TMP/c"),
    ("firmware_export.cli", "c --model A --out TMP/c --spec-toml NONE", ["--spec-toml", "does not exist"], "TMP/c"),
    ("firmware_export.cli", "c --model A --out TMP/c --spec-toml BAD", ["--spec-toml", "not valid TOML"], "TMP/c"),
    ("firmware_export.cli", "c --model A --out TMP/c --app FILE", ["--app", "is a file"], "TMP/c"),
    ("firmware_export.cli", "c --model FILE --out TMP/c", ["FILE", "swarm-export onnx"], "TMP/c"),
    ("firmware_export.cli", "c --model DIR --out TMP/c", ["DIR"], "TMP/c"),
    ("firmware_export.cli", "onnx --run DIR --out FILE", ["--out", "is a file"], None),
    ("firmware_export.cli", "onnx --run DIR --out TMP/o --random 0", ["--random", "'0'"], "TMP/o"),
]


def _fill(text: str, paths: dict) -> str:
    for key in ("FILE", "DIR", "BAD", "NONE", "TMP"):
        text = text.replace(key, paths[key])
    return text


def _token(tok: str, paths: dict) -> str:
    return {"''": "", "M": MODELS, "C": CONFIG, "A": ACTOR}.get(tok) if tok in ("''", "M", "C", "A") \
        else _fill(tok, paths)


@pytest.mark.parametrize("module, argv, needles, absent", CASES, ids=[f"{m.split('.')[0]} {a}" for m, a, _, _ in CASES])
def test_bad_input_is_one_line_exit_2_and_writes_nothing(module, argv, needles, absent, paths, capsys):
    rc, err = _run(module, [_token(t, paths) for t in argv.split()], capsys)
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert _fill(needle, paths) in lines[0], (needle, lines[0])
    if absent is not None:
        assert not Path(_fill(absent, paths)).exists()


def test_the_types_take_what_they_should():
    assert cliutil.probability("0") == 0.0 and cliutil.probability("1") == 1.0
    assert cliutil.float_in(0.0, low_open=True, allow_inf=True)("inf") == math.inf
    assert cliutil.port("1") == 1 and cliutil.port("65535") == 65535
    assert cliutil.float_list(cliutil.probability, "p", "0,1")("0, 0.5") == [0.0, 0.5]
    for bad in ("0", "65536", "-1", "x", "1.5"):
        with pytest.raises(argparse.ArgumentTypeError, match="1..65535"):
            cliutil.port(bad)
    for bad in ("nan", "inf", "-1e-9", "1.0001"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"\[0, 1\]"):
            cliutil.probability(bad)


def test_atomic_write_replaces_whole_files_and_leaves_no_temporary(tmp_path, monkeypatch):
    target = tmp_path / "sub" / "out.json"
    cliutil.write_json_atomic(target, {"a": math.inf, "b": math.nan})
    assert json.loads(target.read_text()) == {"a": "inf", "b": None}

    def broken_replace(src, dst):  # an error (or Ctrl-C) between writing and renaming
        raise KeyboardInterrupt

    monkeypatch.setattr(cliutil.os, "replace", broken_replace)
    with pytest.raises(KeyboardInterrupt):
        cliutil.write_text_atomic(target, "half")
    assert json.loads(target.read_text()) == {"a": "inf", "b": None}  # the old file, whole
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.json"]
