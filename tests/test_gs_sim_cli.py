"""``swarm-gs sim --mavlink N --autopilot {ardupilot,px4}``: the standalone simulator speaks as the chosen
autopilot to an ordinary pymavlink client."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pymavlink = pytest.importorskip("pymavlink")
from pymavlink import mavutil  # noqa: E402

from groundstation.sim.swarm import free_base_port  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("autopilot, expected", [("ardupilot", mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA),
                                                 ("px4", mavutil.mavlink.MAV_AUTOPILOT_PX4)])
def test_sim_heartbeats_as_the_chosen_autopilot(autopilot, expected):
    port = free_base_port(1, seed=hash(autopilot) % 1000)
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255)
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from groundstation.cli import main; sys.exit(main())",
                             "sim", "--drones", "0", "--mavlink", "1", "--mavlink-port", str(port),
                             "--autopilot", autopilot, "--duration", "60"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=45)
        assert hb is not None, proc.stderr.read() if proc.poll() is not None else "no heartbeat in 45 s"
        assert hb.autopilot == expected and hb.type == mavutil.mavlink.MAV_TYPE_QUADROTOR
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        gcs.close()


@pytest.mark.parametrize("args, needle", [(["sim", "--base-port", "70000"], "--base-port"),
                                          (["sim", "--drones", "12", "--base-port", "65530"], "--base-port: 65530"),
                                          (["sim", "--mavlink-port", "0"], "--mavlink-port"),
                                          (["demo", "--base-port", "-1"], "--base-port")])
def test_bad_ports_are_one_line_usage_errors(args, needle, capsys):
    from groundstation.cli import main
    with pytest.raises(SystemExit) as exc:
        code = main(args)
        raise SystemExit(code)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err
