"""swarm-runtime run / degrade end to end with tiny budgets, and its errors."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest

from runtime.cli import JSON_KEYS, main
from tests.runtime_fixtures import exported


@pytest.fixture(scope="module")
def models():
    return exported(False)[1]


def test_run_threads_prints_metrics_and_writes_the_json_keys(models, tmp_path, capsys):
    out = tmp_path / "run.json"
    assert main(["run", "--models", str(models), "--duration", "1.5", "--rate", "20", "--loss", "0.2",
                 "--latency", "0.05", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "min pursuer-target distance" in text and "tick-to-action" in text
    res = json.loads(out.read_text())
    assert set(JSON_KEYS) <= set(res)
    assert res["steps"] >= 10 and res["episodes"] == 1  # the partial episode is scored
    assert res["agent_ticks"] >= 12 * 20 and res["agent_faults"] == 0
    assert 0 < res["tick_to_action_p50_us"] <= res["tick_to_action_p99_us"]
    c = res["comms"]
    assert c["sent"] > 0 and c["delivered"] > 0 and c["dropped_loss"] > 0
    assert res["config"]["loss"] == 0.2 and res["config"]["latency_s"] == 0.05


def test_run_processes_over_udp(models, tmp_path):
    out = tmp_path / "proc.json"
    assert main(["run", "--models", str(models), "--duration", "1.5", "--processes", "--engine", "compiled",
                 "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["config"]["processes"] is True and res["config"]["engine"] == "compiled"
    assert res["steps"] >= 10 and res["agent_ticks"] >= 12 * 10 and res["agent_faults"] == 0
    assert res["comms"]["delivered"] > 0 and res["comms"]["dropped_malformed"] == 0


def test_degrade_writes_the_table(models, tmp_path):
    out = tmp_path / "deg"
    assert main(["degrade", "--models", str(models), "--duration", "1", "--losses", "0,0.5", "--latencies", "0.05",
                 "--baseline-repeats", "1", "--out", str(out)]) == 0
    doc = json.loads(out.with_suffix(".json").read_text())
    assert [(r["loss"], r["latency_s"]) for r in doc["rows"]] == [(0.0, 0.05), (0.5, 0.05)]
    assert [(r["loss"], r["latency_s"]) for r in doc["baseline_repeats"]] == [(0.0, 0.05)]
    assert doc["rows"][1]["delivered_fraction"] < doc["rows"][0]["delivered_fraction"] == 1.0
    md = out.with_suffix(".md").read_text()
    assert "| 0.5 | 50 |" in md and "tracking" in md and "Run-to-run spread" in md


def test_bench_times_every_engine_and_the_loop(models, tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "--models", str(models), "--agent", "11", "--calls", "500", "--loop-seconds", "0.5",
                 "--rate", "50", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "evader_1" in text and "compiled" in text and "onnxruntime default" in text and "deadline misses" in text
    res = json.loads(out.read_text())
    assert set(res["engines"]) == {"compiled", "onnxruntime tuned", "onnxruntime default"}
    for name, r in res["engines"].items():
        assert 0 < r["min_us"] <= r["p50_us"] <= r["p99_us"], name
    assert res["engines"]["compiled"]["parity_vs_onnxruntime"] <= 1e-5
    assert res["engines"]["onnxruntime tuned"]["cold_p50_us"] > 0
    assert [r["engine"] for r in res["loops"]] == ["compiled", "onnxruntime"]
    assert all(r["agent_ticks"] >= 12 * 10 and r["agent_faults"] == 0 for r in res["loops"])
    bad = _cli("bench", "--models", str(models), "--agent", "12")
    assert bad.returncode == 2 and "--agent: 12" in bad.stderr and "Traceback" not in bad.stderr


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "runtime.cli", *args], capture_output=True, text=True, timeout=120)


def test_bad_models_folder_exits_nonzero_with_the_named_error(models, tmp_path):
    r = _cli("run", "--models", str(tmp_path / "missing"), "--duration", "1")
    assert r.returncode == 2 and "ModelNotFound" in r.stderr and "swarm-export onnx" in r.stderr
    assert "Traceback" not in r.stderr
    broken = tmp_path / "broken"
    shutil.copytree(models, broken)
    victim = sorted(broken.glob("*.onnx"))[3]
    victim.write_bytes(victim.read_bytes()[:-10] + b"0123456789")
    for extra in ([], ["--processes"]):
        r = _cli("run", "--models", str(broken), "--duration", "1", *extra)
        assert r.returncode == 2 and "ModelCorrupted" in r.stderr and victim.name in r.stderr
        assert "Traceback" not in r.stderr


def test_bad_arguments_are_refused(models):
    for args in (["--loss", "1.5"], ["--latency", "-1"], ["--rate", "0"]):
        with pytest.raises(SystemExit) as e:
            main(["run", "--models", str(models), *args])
        assert e.value.code == 2
