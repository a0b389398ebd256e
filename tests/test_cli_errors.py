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
PAPER_MODELS = str(ROOT / "models" / "paper_role_based")  # the default spec's models (a fleet file without spec)
ACTOR = str(ROOT / "models" / "role_based" / "pursuer_0.onnx")
CONFIG = str(ROOT / "configs" / "role_based.toml")
OTHER_SPEC = str(ROOT / "configs" / "multi_target.toml")  # not the spec of models/role_based


@pytest.fixture
def paths(tmp_path, monkeypatch):
    """A file (``FILE``), a folder (``DIR``), a broken TOML (``BAD``), a missing path (``NONE``), a file that is
    not UTF-8 (``BINTOML``) and config files with one wrong key or value each (``*KEY``, ``FLEETMODELS``,
    ``FLEETSPEC``)."""
    monkeypatch.chdir(ROOT)  # the commands' defaults (configs/..., models/...) are relative to the repository
    (tmp_path / "afile").write_text("x\n")
    (tmp_path / "adir").mkdir()
    (tmp_path / "bad.toml").write_text("not = [toml\n")
    (tmp_path / "bin.toml").write_bytes(b"\xff\xfe[spec]\n")
    (tmp_path / "fence_key.toml").write_text("[fence]\nmarginn = 0.1\n")
    (tmp_path / "fence_small.toml").write_text("[fence]\nbox = [-2.5, 2.5, -2.5, 2.5]\nmargin = 0.2\n")
    (tmp_path / "sep_key.toml").write_text("[separation]\nmin_dist = 0.5\n")
    (tmp_path / "train_key.toml").write_text("[train]\nstepz = 5\n")
    (tmp_path / "train_seed.toml").write_text("[train]\nseed = -1\n")
    (tmp_path / "fleet_key.toml").write_text("[fleet]\ntelemetry_period = 20\n")
    (tmp_path / "fleet_models.toml").write_text(
        f'[fleet]\nmodels = "{tmp_path / "adir"}"\nfence = "{ROOT / "configs" / "fence.toml"}"\n'
        '[[fleet.drones]]\nid = "cf1"\nuri = "radio://0/80/2M/E7E7E7E701"\nteam = "pursuer"\n')
    (tmp_path / "fleet_fence.toml").write_text(
        f'[fleet]\nmodels = "{PAPER_MODELS}"\nfence = "{tmp_path / "fence_small.toml"}"\n'
        '[[fleet.drones]]\nid = "cf1"\nuri = "radio://0/80/2M/E7E7E7E701"\nteam = "pursuer"\n')
    (tmp_path / "fleet_spec.toml").write_text(
        f'[fleet]\nmodels = "{MODELS}"\nspec = "{OTHER_SPEC}"\nfence = "{ROOT / "configs" / "fence.toml"}"\n'
        '[[fleet.drones]]\nid = "cf1"\nuri = "radio://0/80/2M/E7E7E7E701"\nteam = "pursuer"\n')
    (tmp_path / "empty.toml").write_text("# nothing but a comment\n")
    (tmp_path / "fleet_uri.toml").write_text(
        f'[fleet]\nmodels = "{MODELS}"\nfence = "{ROOT / "configs" / "fence.toml"}"\n'
        '[[fleet.drones]]\nid = "cf1"\nuri = "bogus://x"\nteam = "pursuer"\n')
    (tmp_path / "mini.jsonl").write_text('{"t": 0.0, "drone": "cf0", "state": "flying", "position": [0, 0, 0.5]}\n'
                                         '{"t": 2.0, "drone": "cf0", "state": "flying", "position": [0.1, 0, 0.5]}\n')
    (tmp_path / "runcut" / "checkpoints").mkdir(parents=True)  # a run whose training state was cut short
    (tmp_path / "runcut" / "config.toml").write_text((ROOT / "configs" / "multi_target.toml").read_text())
    (tmp_path / "runcut" / "checkpoints" / "state.pt").write_bytes(b"PK\x03\x04 cut short")
    (tmp_path / "runcsv").mkdir()
    (tmp_path / "runcsv" / "metrics.csv").write_text("env_step\n")
    return {"FILE": str(tmp_path / "afile"), "DIR": str(tmp_path / "adir"), "BAD": str(tmp_path / "bad.toml"),
            "NONE": str(tmp_path / "none"), "TMP": str(tmp_path), "BINTOML": str(tmp_path / "bin.toml"),
            "FENCEKEY": str(tmp_path / "fence_key.toml"), "SEPKEY": str(tmp_path / "sep_key.toml"),
            "FENCESMALL": str(tmp_path / "fence_small.toml"), "FLEETFENCE": str(tmp_path / "fleet_fence.toml"),
            "TRAINKEY": str(tmp_path / "train_key.toml"), "TRAINSEED": str(tmp_path / "train_seed.toml"),
            "FLEETKEY": str(tmp_path / "fleet_key.toml"),
            "FLEETMODELS": str(tmp_path / "fleet_models.toml"), "FLEETSPEC": str(tmp_path / "fleet_spec.toml"),
            "EMPTY": str(tmp_path / "empty.toml"), "FLEETURI": str(tmp_path / "fleet_uri.toml"),
            "MINILOG": str(tmp_path / "mini.jsonl"), "RUNCUT": str(tmp_path / "runcut"),
            "RUNCSV": str(tmp_path / "runcsv")}


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
    ("runtime.cli", "degrade --models M --baseline-repeats -1", ["--baseline-repeats", "'-1'", "0..100"], None),
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
    ("runtime.cli", "run --models NONE", ["--models", "ModelNotFound", "swarm-export onnx"], None),
    ("runtime.cli", "run --models DIR", ["--models", "manifest.json", "swarm-export onnx"], None),
    ("runtime.cli", "run --models M --seed -1", ["--seed", "'-1'", ">= 0"], None),
    ("runtime.cli", "run --models M --engine gpu", ["--engine", "'gpu'"], None),
    ("training.cli", "evaluate --json FILE/e.json --episodes 1", ["--json", "is a file"], "FILE/e.json"),
    ("training.cli", "evaluate --md FILE/e.md --episodes 1", ["--md", "is a file"], "FILE/e.md"),
    ("training.cli", "evaluate --plot DIR --episodes 1", ["--plot", "is a folder"], None),
    ("training.cli", "evaluate --episodes 0", ["--episodes", "'0'", "1..1000000"], None),
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
    ("firmware_export.cli", "c --model A --out TMP/c --spec-toml FENCEKEY", ["--spec-toml", "no [spec] table"],
     "TMP/c"),
    ("firmware_export.cli", "c --model A --out TMP/c --app FILE", ["--app", "is a file"], "TMP/c"),
    ("firmware_export.cli", "c --model FILE --out TMP/c", ["FILE", "swarm-export onnx"], "TMP/c"),
    ("firmware_export.cli", "c --model DIR --out TMP/c", ["DIR"], "TMP/c"),
    ("firmware_export.cli", "onnx --run DIR --out FILE", ["--out", "is a file"], None),
    ("firmware_export.cli", "onnx --run DIR --out TMP/o --random 0", ["--random", "'0'"], "TMP/o"),
    ("firmware_export.cli", "onnx --run FILE --out TMP/o", ["--run", "is a file", "swarm-train train"], "TMP/o"),
    ("firmware_export.cli", "onnx --run DIR --out TMP/o --seed -1", ["--seed", "'-1'"], "TMP/o"),
    ("runtime.cli", "run --models FILE", ["--models", "is a file", "swarm-export onnx"], None),
    ("training.cli", "train --config TRAINKEY --out TMP/r", ["TRAINKEY: train.stepz", "valid keys"], "TMP/r"),
    ("training.cli", "train --config C --out TMP/r --seed -1", ["--seed", ">= 0", "-1"], "TMP/r"),
    ("training.cli", "train --config TRAINSEED --out TMP/r", ["TRAINSEED: train.seed", ">= 0"], "TMP/r"),
    ("training.cli", "evaluate --seed -5 --episodes 1", ["--seed", "'-5'", ">= 0"], None),
    ("training.cli", "plot --seed -5 --out TMP/p.png", ["--seed", "'-5'"], "TMP/p.png"),
    ("training.cli", "crossplay M --seed -5", ["--seed", ">= 0", "-5"], None),
    ("training.cli", "evaluate --config BINTOML --episodes 1", ["BINTOML", "not valid TOML"], None),
    ("training.cli", "evaluate --plot TMP/e.txt --episodes 1", ["--plot", "'.txt'", ".png"], "TMP/e.txt"),
    ("training.cli", "plot --out TMP/p.txt", ["--out", "'.txt'", ".png"], "TMP/p.txt"),
    ("training.cli", "plot --run FILE", ["--run", "is a file", "swarm-train train"], "FILE/plots"),
    # swarm-gs: every one fails before a simulator starts (a demo that passed its checks would fly for 30 s)
    ("groundstation.cli", "sim --base-port 70000", ["--base-port", "'70000'", "1..65535"], None),
    ("groundstation.cli", "sim --drones 12 --base-port 65530", ["--base-port", "65524"], None),
    ("groundstation.cli", "sim --drones -1", ["--drones", "'-1'", ">= 0"], None),
    ("groundstation.cli", "sim --drones 0", ["--drones 0", "at least one"], None),
    ("groundstation.cli", "sim --spacing 0", ["--spacing", "'0'", "> 0"], None),
    ("groundstation.cli", "sim --duration inf", ["--duration", "'inf'", "finite"], None),
    ("groundstation.cli", "sim --seed -1", ["--seed", "'-1'"], None),
    ("groundstation.cli", "sim --host 999.1.1.1", ["--host", "'999.1.1.1'", "127.0.0.1"], None),
    ("groundstation.cli", "demo --base-port -1", ["--base-port", "'-1'", "1..65535"], None),
    ("groundstation.cli", "demo --models M --base-port 65530", ["--base-port", "12 drones", "65524"], None),
    ("groundstation.cli", "demo --models M --json FILE/x.json", ["--json", "is a file"], "FILE/x.json"),
    ("groundstation.cli", "demo --models M --json DIR", ["--json", "is a folder"], None),
    ("groundstation.cli", "demo --models M --log FILE/f.jsonl", ["--log", "is a file"], "FILE/f.jsonl"),
    ("groundstation.cli", "demo --models M --plot TMP/p.txt", ["--plot", "'.txt'", ".png"], "TMP/p.txt"),
    ("groundstation.cli", "demo --models M --duration 0", ["--duration", "'0'", "> 0"], None),
    ("groundstation.cli", "demo --models M --duration nan", ["--duration", "'nan'"], None),
    ("groundstation.cli", "demo --models M --speed -1", ["--speed", "'-1'", "> 0"], None),
    ("groundstation.cli", "demo --models M --loss 1", ["--loss", "[0, 1)", "got 1"], None),
    ("groundstation.cli", "demo --models M --seed -1", ["--seed", "'-1'"], None),
    ("groundstation.cli", "demo --models M --telemetry-period-ms 5", ["--telemetry-period-ms", "'5'", "10..1000"],
     None),
    ("groundstation.cli", "demo --models M --kill-link 3@40", ["--kill-link", "3@40", "--duration"], None),
    ("groundstation.cli", "demo --models M --kill-link cf99@1", ["--kill-link", "'cf99'", "cf0"], None),
    ("groundstation.cli", "demo --kill-link 3", ["--kill-link", "DRONE@SECONDS"], None),
    ("groundstation.cli", "demo --models FILE", ["--models", "is a file", "swarm-export onnx"], None),
    ("groundstation.cli", "demo --models DIR", ["--models", "manifest.json", "swarm-export onnx"], None),
    ("groundstation.cli", "demo --models M --engine gpu", ["--engine", "'gpu'"], None),
    ("groundstation.cli", "demo --models M --fence NONE", ["--fence", "NONE", "does not exist"], None),
    ("groundstation.cli", "demo --models M --fence FENCEKEY", ["--fence", "fence.marginn", "valid keys"], None),
    ("groundstation.cli", "demo --models M --fence FENCESMALL", ["--fence FENCESMALL", "cuts 0.50 m into the arena",
                                                                 f"the models in {MODELS}", "[-3.0, 3.0]^2", "margin 0.2"],
     None),
    ("groundstation.cli", "demo --models M --anchors BAD", ["--anchors", "not valid TOML"], None),
    ("groundstation.cli", "demo --models M --flight-config SEPKEY", ["--flight-config", "separation.min_dist",
                                                                     "valid keys"], None),
    ("groundstation.cli", "demo --models M --flight-config DIR", ["--flight-config", "is a folder"], None),
    ("groundstation.cli", "demo --models M --spec BINTOML", ["--spec", "not valid TOML"], None),
    ("groundstation.cli", "demo --models M --fence BINTOML", ["--fence", "not valid TOML"], None),
    ("groundstation.cli", "demo --models M --fence TRAINKEY", ["--fence", "TRAINKEY", "no [fence] table"], None),
    ("groundstation.cli", "demo --models M --anchors FENCEKEY", ["--anchors", "no [lps] table"], None),
    ("groundstation.cli", "demo --models M --spec FENCEKEY", ["--spec", "no [spec] table"], None),
    ("groundstation.cli", "demo --models M --flight-config FENCEKEY", ["--flight-config", "no [flight] or "
                                                                                          "[separation] table"], None),
    ("groundstation.cli", "demo --models M --spec S2", ["--spec", "exported for spec", "leave --spec out"], None),
    ("groundstation.cli", "fly --fleet NONE", ["--fleet", "does not exist"], None),
    ("groundstation.cli", "fly --fleet NONE --duration 0", ["--duration", "'0'"], None),
    ("groundstation.cli", "fly --fleet FLEETKEY", ["--fleet", "fleet.telemetry_period", "valid keys"], None),
    ("groundstation.cli", "fly --fleet FLEETMODELS", ["--fleet", "fleet.models", "manifest.json"], None),
    ("groundstation.cli", "fly --fleet FLEETSPEC", ["--fleet", "fleet.spec", "exported for spec"], None),
    ("groundstation.cli", "fly --fleet FLEETFENCE", ["--fleet", "fleet.fence FENCESMALL", "cuts 0.50 m into the arena",
                                                     f"the models in {PAPER_MODELS}"], None),
    ("groundstation.cli", "fly --fleet BAD --log FILE/f.jsonl", ["--log", "is a file"], "FILE/f.jsonl"),
    ("groundstation.cli", "status --fleet DIR", ["--fleet", "is a folder"], None),
    ("groundstation.cli", "land --fleet BAD", ["--fleet", "not valid TOML"], None),
    # issue 12's second pass: numbers past what the machine can hold or a typo, '' read as "not given", a seed
    # torch cannot take, a config with nothing in it, damaged checkpoints, overrides of an actor's own metadata
    ("runtime.cli", "run --models M --rate 1e9", ["--rate", "'1e9'", "(0, 1000]"], None),
    ("runtime.cli", "run --models M --duration 1e300", ["--duration 1e+300", "control ticks", "1000000"], None),
    ("runtime.cli", "run --models M --duration 0.5 --rate 0.001", ["--duration 0.5", "less than one control tick"],
     None),
    ("runtime.cli", "run --models M --seed 99999999999999999999999", ["--seed", "4294967295"], None),
    ("runtime.cli", "run --models ''", ["--models", "got ''"], None),
    ("runtime.cli", "degrade --models M --baseline-repeats 99999999999", ["--baseline-repeats", "0..100"], None),
    ("runtime.cli", "degrade --models M --out ''", ["--out", "got ''"], None),
    ("runtime.cli", "degrade --models M --duration 1e300 --out TMP/d", ["--duration", "control ticks"], "TMP/d.md"),
    ("runtime.cli", "bench --models M --calls 99999999999999", ["--calls", "100..10000000"], None),
    ("runtime.cli", "bench --models M --loop-seconds 1e300", ["--loop-seconds", "control ticks"], None),
    ("runtime.cli", "bench --models M --rate 1e12", ["--rate", "(0, 1000]"], None),
    ("runtime.cli", "bench --models FILE", ["--models", "is a file"], None),
    ("firmware_export.cli", "c --model A --out TMP/c --calib-obs 99999999999999", ["--calib-obs", "1..1000000"],
     "TMP/c"),
    ("firmware_export.cli", "c --model A --out TMP/c --report --report-obs 999999999999999",
     ["--report-obs", "1..1000000"], "TMP/c"),
    ("firmware_export.cli", "onnx --run DIR --out TMP/o --random 999999999999999", ["--random", "1..1000000"],
     "TMP/o"),
    ("firmware_export.cli", "onnx --run DIR --out TMP/o --recorded 999999999999999", ["--recorded", "1..1000000"],
     "TMP/o"),
    ("firmware_export.cli", "c --model A --out TMP/c --spec-toml S2", ["--spec-toml", "exported for spec",
                                                                      "leave --spec-toml out"], "TMP/c"),
    ("firmware_export.cli", "c --model A --out TMP/c --role scout", ["--role scout", "pursuer actor",
                                                                    "leave --role out"], "TMP/c"),
    ("training.cli", "train --config EMPTY --out TMP/r", ["--config", "is empty", "configs/role_based.toml"], "TMP/r"),
    ("training.cli", "train --config '' --out TMP/r", ["--config", "got ''"], "TMP/r"),
    ("training.cli", "train --config C --out TMP/r --seed 99999999999999999999999", ["--seed", "4294967295"],
     "TMP/r"),
    ("training.cli", "train --config C --out TMP/r --n-envs 99999999999", ["--n-envs", "1..65536"], "TMP/r"),
    ("training.cli", "train --config C --out TMP/r --threads 99999", ["--threads", "1..256"], "TMP/r"),
    ("training.cli", "train --config C --out TMP/r --init-from RUNCUT", ["--init-from", "state.pt", "is damaged"],
     "TMP/r"),
    ("training.cli", "train --out RUNCUT --resume", ["--resume", "state.pt", "is damaged"], None),
    ("training.cli", "evaluate --config EMPTY --episodes 1", ["--config", "is empty"], None),
    ("training.cli", "evaluate --episodes 99999999999999", ["--episodes", "1..1000000"], None),
    ("training.cli", "evaluate --episodes 1 --n-envs 99999999999", ["--n-envs", "1..65536"], None),
    ("training.cli", "evaluate --episodes 1 --seed 99999999999999999999999", ["--seed", "4294967295"], None),
    ("training.cli", "crossplay M --episodes 99999999999", ["--episodes", "1..1000000"], None),
    ("training.cli", "crossplay M --episodes 1 --n-envs 99999999999", ["--n-envs", "1..65536"], None),
    ("training.cli", "crossplay M --episodes 1 --seed 99999999999999999999999", ["--seed", "4294967295"], None),
    ("training.cli", "plot --run NONE", ["--run", "not a training run folder"], "NONE"),
    ("training.cli", "crossplay M models/role_based --episodes 1", ["RUN_OR_MODELS", "same folder as", "once"], None),
    ("training.cli", "evaluate --models M --run M --episodes 1", ["--run/--models", "same folder as"], None),
    ("training.cli", "plot --run RUNCSV --out ''", ["--out", "got ''"], "RUNCSV/plots"),
    ("training.cli", "sweep --steps 1 --ray ''", ["--ray", "got ''"], None),
    ("training.cli", "sweep --steps 1 --ray bogus://x", ["--ray", "'bogus://x'", "ray://HOST:PORT"], None),
    ("training.cli", "sweep --steps 1 --workers 99999", ["--workers", "'99999'"], None),
    ("groundstation.cli", "sim --drones 99999999", ["--drones 99999999", "more drones than UDP ports"], None),
    ("groundstation.cli", "sim --drones 0 --mavlink 99999999", ["--mavlink 99999999", "more drones than UDP ports"],
     None),
    ("groundstation.cli", "sim --drones 1 --mavlink 1 --base-port 14550 --mavlink-port 14550",
     ["--mavlink-port 14550", "overlap", "--base-port"], None),
    ("groundstation.cli", "sim --seed 99999999999999999999999", ["--seed", "4294967295"], None),
    ("groundstation.cli", "demo --models M --seed 99999999999999999999999", ["--seed", "4294967295"], None),
    ("groundstation.cli", "demo --models M --spec ''", ["--spec", "got ''", "leave --spec out"], None),
    ("groundstation.cli", "demo --models M --flight-config ''", ["--flight-config", "got ''"], None),
    ("groundstation.cli", "demo --models M --fence ''", ["--fence", "got ''"], None),
    ("groundstation.cli", "fly --fleet FLEETURI", ["fleet.drones[0].uri", "'bogus://x'", "radio://"], None),
    ("groundstation.cli", "land --fleet FLEETURI", ["fleet.drones[0].uri", "no known link scheme"], None),
    ("groundstation.cli", "status --fleet FLEETURI", ["fleet.drones[0].uri", "no known link scheme"], None),
    ("groundstation.cli", "replay MINILOG --start 5 --once", ["--start 5", "past the end", "2.0 s"], None),
    ("groundstation.cli", "replay ''", ["LOG", "got ''"], None),
]


def _fill(text: str, paths: dict) -> str:
    for key in sorted(paths, key=len, reverse=True):  # FLEETMODELS before any shorter name
        text = text.replace(key, paths[key])
    return text


def _token(tok: str, paths: dict) -> str:
    fixed = {"''": "", "M": MODELS, "C": CONFIG, "A": ACTOR, "S2": OTHER_SPEC}
    return fixed[tok] if tok in fixed else _fill(tok, paths)


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


PROC_CASES = [("runtime.cli", "run --models M --json /proc/x.json"),
              ("groundstation.cli", "demo --models M --log /proc/x.jsonl"),
              ("groundstation.cli", "report MINILOG --plot /proc/r.png"),
              ("training.cli", "train --config C --out /proc/r"),
              ("training.cli", "evaluate --episodes 1 --json /proc/e.json"),
              ("firmware_export.cli", "c --model A --out /proc/c")]


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
@pytest.mark.parametrize("module, argv", PROC_CASES, ids=[f"{m.split('.')[0]} {a}" for m, a in PROC_CASES])
def test_an_output_in_a_folder_nobody_can_write_is_a_usage_error(module, argv, paths, capsys):
    """/proc takes no new files even from root, for whom ``os.access`` says yes: the check creates a probe file,
    so that the write does not fail only after the run (as it did with exit status 1)."""
    rc, err = _run(module, [_token(t, paths) for t in argv.split()], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert "/proc" in err and "not writable" in err, err


@pytest.mark.parametrize("damage, needle", [("delete", "no ONNX model at"), ("overwrite", "sha256 differs")])
def test_a_missing_or_replaced_actor_fails_before_any_link_opens(damage, needle, tmp_path, capsys, monkeypatch):
    """``load_models`` would find it only after the simulators (or radios) are up and preflight passed."""
    import shutil
    monkeypatch.chdir(ROOT)
    models = tmp_path / "models"
    shutil.copytree(MODELS, models)
    actor = models / "pursuer_0.onnx"
    actor.unlink() if damage == "delete" else actor.write_bytes(b"not the exported actor")
    fleet = tmp_path / "fleet.toml"
    fleet.write_text(f'[fleet]\nmodels = "{models}"\nfence = "{ROOT / "configs" / "fence.toml"}"\n[[fleet.drones]]\n'
                     'id = "cf1"\nuri = "radio://0/80/2M/E7E7E7E701"\nteam = "pursuer"\n')
    for argv, option in ((["demo", "--models", str(models)], "--models"), (["fly", "--fleet", str(fleet)],
                                                                            "fleet.models")):
        rc, err = _run("groundstation.cli", argv, capsys)
        assert rc == 2 and len(err.strip().splitlines()) == 1, err
        assert option in err and needle in err and "pursuer_0.onnx" in err and "swarm-export onnx" in err, err


@pytest.mark.parametrize("module, argv, option", [("groundstation.cli", ["demo"], "--models"),
                                                  ("groundstation.cli", ["demo", "--models", MODELS], "--fence"),
                                                  ("training.cli", ["evaluate", "--episodes", "1"], "--config"),
                                                  ("training.cli", ["sweep", "--steps", "1"], "--config")])
def test_a_default_relative_to_the_repository_names_its_option_elsewhere(module, argv, option, tmp_path, capsys,
                                                                         monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc, err = _run(module, argv, capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert option in err and str(tmp_path) in err and "Traceback" not in err, err


def test_the_types_take_what_they_should():
    assert cliutil.probability("0") == 0.0 and cliutil.probability("1") == 1.0
    assert cliutil.float_in(0.0, 1.0, high_open=True)("0.999") == 0.999
    assert cliutil.int_in(10, 1000)("10") == 10 and cliutil.int_in(10, 1000)("1000") == 1000
    assert cliutil.out_picture("x.PNG").name == "x.PNG"
    for bad in ("1", "1.5", "nan"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"\[0, 1\)"):
            cliutil.float_in(0.0, 1.0, high_open=True)(bad)
    for bad in ("9", "1001", "x"):
        with pytest.raises(argparse.ArgumentTypeError, match="10..1000"):
            cliutil.int_in(10, 1000)(bad)
    assert cliutil.float_in(0.0, low_open=True, allow_inf=True)("inf") == math.inf
    assert cliutil.port("1") == 1 and cliutil.port("65535") == 65535
    assert cliutil.seed("0") == 0 and cliutil.seed(str(cliutil.SEED_MAX)) == cliutil.SEED_MAX
    for bad in ("-1", str(cliutil.SEED_MAX + 1), "1.5", ""):
        with pytest.raises(argparse.ArgumentTypeError, match=">= 0 and <= 4294967295"):
            cliutil.seed(bad)
    args = argparse.Namespace(n_envs=70000, seed=None, flag=True)
    with pytest.raises(argparse.ArgumentTypeError, match="^--n-envs: .*1..65536.*'70000'"):
        cliutil.recheck(args, "n_envs", cliutil.int_in(1, 65536))
    cliutil.recheck(args, "seed", cliutil.seed)  # not given: nothing to check
    cliutil.recheck(args, "flag", cliutil.seed)  # a switch is not a number
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


def test_atomic_path_renames_on_success_and_removes_the_temporary_on_error(tmp_path):
    target = tmp_path / "sub" / "plot.png"
    with cliutil.atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp.suffix == ".png"  # savefig picks the format from it
        tmp.write_bytes(b"whole")
    assert target.read_bytes() == b"whole"
    with pytest.raises(KeyboardInterrupt):
        with cliutil.atomic_path(target) as tmp:
            tmp.write_bytes(b"ha")  # Ctrl-C half-way through the drawing
            raise KeyboardInterrupt
    assert target.read_bytes() == b"whole" and sorted(p.name for p in target.parent.iterdir()) == ["plot.png"]
