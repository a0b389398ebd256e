"""``swarm-gs demo`` end to end in a subprocess: 12 simulated Crazyflies through cflib, a short mission."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytest.importorskip("cflib")

from flight_fixtures import quick_flight_toml, write_models  # noqa: E402
from groundstation import cli  # noqa: E402
from groundstation.demo import RESULT_KEYS  # noqa: E402


def _demo(*args: str, timeout: float = 90) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "groundstation.cli", "demo", *args], capture_output=True,
                          text=True, timeout=timeout)


def test_short_demo_flies_loses_a_link_lands_and_reports(tmp_path):
    models = write_models(tmp_path / "models")
    out = tmp_path / "out"
    r = _demo("--duration", "3", "--models", str(models), "--json", str(out / "demo.json"),
              "--log", str(out / "flight.jsonl"), "--plot", str(out / "demo.png"), "--seed", "7",
              "--kill-link", "cf4@0.5", "--engine", "compiled",
              "--flight-config", str(quick_flight_toml(tmp_path / "flight.toml")))  # what is tested is not the pace
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads((out / "demo.json").read_text())
    assert res["engine"] == "compiled"
    for key in RESULT_KEYS:
        assert key in res, key
    # cf4's link is cut: detected, and its firmware's watchdog brings it down (locked); the others land
    assert res["landed"] == 12 and res["locked"] == 1 and res["final_truth"]["cf4"]["supervisor"] == "locked"
    assert res["kill_link"]["drone"] == "cf4" and 0 < res["kill_link"]["detected_after_ms"] < 300
    assert res["final_status"]["cf4"] == "lost" and any("cf4" in c for c in res["role_changes"])
    assert res["geofence_violations"] == 0
    assert res["episodes"] == 1 and res["control_periods"] >= 25
    assert 0.0 <= res["tracking_rate"] <= 1.0 and 0.0 < res["coverage"] <= 1.0
    assert 0.0 < res["mean_min_dist"] <= res["mean_avg_dist"] <= res["mean_max_dist"]
    assert res["setpoints"] > 12 * 2 * 15  # 20 Hz per drone
    # measured at the simulated drones (the yaw rate carries the measurement's timestamp)
    assert res["setpoint_latency_samples"] > res["setpoints"] / 2
    assert 0 < res["setpoint_latency_p50_ms"] <= res["setpoint_latency_p99_ms"]
    assert 0 < res["ground_station_latency_p50_ms"] <= res["ground_station_latency_p99_ms"]
    assert {d: v for d, v in res["final_status"].items() if d != "cf4"} == {f"cf{i}": "landed" for i in range(12)
                                                                          if i != 4}
    agents = res["agents"]
    assert agents["actions"] > 0 and agents["faults"] == agents["no_state"]  # no policy faults
    # telemetry every 20 ms: at most 50/s on every live link, a dead link none. How many fewer arrive is the
    # machine's speed (the simulators' one process falls behind: 10/s measured under make test-under-load), so
    # the rate itself is a benchmark's figure, not this test's
    live = {d: v["telemetry_per_s"] for d, v in res["links"]["per_drone"].items() if d != "cf4"}
    assert res["links"]["telemetry_period_ms"] == 20
    assert all(0 < rate <= 50 * 1.2 for rate in live.values()), res["links"]["per_drone"]
    assert res["links"]["per_drone"]["cf4"]["link_lost"]
    assert "landed 12/12 (1 locked)" in r.stdout and "geofence violations 0" in r.stdout
    rows = [json.loads(line) for line in (out / "flight.jsonl").read_text().splitlines()]
    state_rows = [row for row in rows if "event" not in row]
    assert {row["drone"] for row in state_rows} == {f"cf{i}" for i in range(12)}
    for key in ("t", "drone", "role", "state", "position", "setpoint", "battery", "link_quality"):
        assert key in state_rows[0]
    flying = [row for row in state_rows if row["state"] == "flying" and row["role"]]
    assert {row["role"] for row in flying} == {"pursuer", "scout", "evader"}
    assert any(row.get("event") == "mission_start" for row in rows)
    assert (out / "demo.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # separation: on by default, every flying setpoint through it; contacts counted by the simulator
    sep = res["separation"]
    assert sep["enabled"] and sep["solves"] > 0 and sum(sep["methods"].values()) == sep["solves"]
    assert res["drone_contacts"] == 0 and res["pairs_touching"] == 0
    assert res["min_pair_distance"] > 0 and res["capture_distance"] == 0.5 and res["min_distance"] == 0.35
    assert "separation on (min 0.35 m): drone contacts 0" in r.stdout and "(within 0.50 m)" in r.stdout
    contact_rows = [row for row in rows if row.get("event") == "drone_contacts"]
    assert len(contact_rows) == 1 and contact_rows[0]["count"] == 0


def test_demo_usage_errors_are_one_line(tmp_path, capsys):
    assert cli.main(["demo", "--models", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert "swarm-export onnx" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as exit_:
        cli.main(["demo", "--kill-link", "3"])
    assert exit_.value.code == 2 and "DRONE@SECONDS" in capsys.readouterr().err
    models = write_models(tmp_path / "models")
    assert cli.main(["demo", "--models", str(models), "--loss", "1.5"]) == 2
    assert "--loss" in capsys.readouterr().err
    assert cli.main(["demo", "--models", str(models), "--kill-link", "cf99@1"]) == 2
    assert "cf99" in capsys.readouterr().err


def test_no_separation_is_for_comparison_only(capsys):
    args = cli.build_parser().parse_args(["demo", "--no-separation"])
    assert args.no_separation
    assert not cli.build_parser().parse_args(["fly", "--fleet", "x.toml"]).no_separation
    with pytest.raises(SystemExit):
        cli.main(["demo", "--help"])
    assert "comparison only" in " ".join(capsys.readouterr().out.split())


def _busy_machine(n: int) -> list[subprocess.Popen]:
    """``n`` processes that keep a core busy each (Debian's stress-ng where installed, else a Python spin)."""
    import shutil
    if shutil.which("stress-ng"):
        return [subprocess.Popen(["stress-ng", "--cpu", str(n), "--quiet"], stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL, start_new_session=True)]
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True) for _ in range(n)]


def test_a_cold_start_on_a_busy_machine_delays_the_mission_and_faults_no_drone(tmp_path):
    """The first run on a fresh machine: numba compiles every kernel (empty NUMBA_CACHE_DIR), onnxruntime makes
    its first calls and both cores are busy. The mission clock waits for every runtime's first command, so no
    healthy drone is landed for "no command from its runtime"."""
    import os
    import signal
    models = write_models(tmp_path / "models")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"))  # cold: nothing compiled yet
    busy = _busy_machine(2)
    try:
        r = subprocess.run([sys.executable, "-m", "groundstation.cli", "demo", "--duration", "2",
                            "--models", str(models), "--json", str(tmp_path / "demo.json"), "--seed", "3",
                            "--flight-config", str(quick_flight_toml(tmp_path / "flight.toml"))],
                           capture_output=True, text=True, timeout=300, env=env)
    finally:
        for p in busy:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads((tmp_path / "demo.json").read_text())
    faults = [e for e in res["events"] if e["kind"] == "agent_fault"]
    assert faults == [], faults
    assert res["final_status"] == {f"cf{i}": "landed" for i in range(12)}
    assert res["startup_s"] >= 0.0 and res["agents"]["actions"] > 0
