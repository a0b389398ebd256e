"""The simulated MAVLink vehicle behaves as ArduCopter or PX4 for clients that are not ours.

The first tests run ordinary pymavlink scripts (``mavutil`` with its default dialect, as the ArduPilot and
PX4 guides write them) in their own interpreter against the simulator: they must fly it and leave it
disarmed. The others check firmware rules one at a time through raw pymavlink or ``MavlinkLink``.
"""
from __future__ import annotations

import functools
import math
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from flight_fixtures import stream as _stream, stream_until, wait_until  # noqa: E402
from groundstation.link import FlightState, LinkError, open_link  # noqa: E402
from groundstation.mavlink_autopilot import (PX4_MAIN_AUTO, PX4_SUB_LOITER, Autopilot, mode_name,  # noqa: E402
                                             px4_custom_mode, px4_split)
from groundstation.sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig, VehicleMode  # noqa: E402
from groundstation.sim.swarm import free_base_port  # noqa: E402

_wait = functools.partial(wait_until, period=0.01)

# An ArduCopter guided flight the way ArduPilot's "Copter Commands in Guided Mode" page and most pymavlink
# examples write it. Everything it waits for has a deadline, so a vehicle that misbehaves fails the test
# instead of hanging it.
ARDUCOPTER_SCRIPT = """
import sys, time
from pymavlink import mavutil

def wait(conn, kind, cond=lambda m: True, timeout=10.0):
    end = time.time() + timeout
    while time.time() < end:
        m = conn.recv_match(type=kind, blocking=True, timeout=0.5)
        if m is not None and cond(m):
            return m
    sys.exit(f"timed out waiting for {kind}")

def latest(conn):
    # the newest LOCAL_POSITION_NED: read what queued up while the script was busy
    while conn.recv_match(blocking=False) is not None:
        pass
    return conn.messages["LOCAL_POSITION_NED"]

def ack(conn, command):
    m = wait(conn, "COMMAND_ACK", lambda m: m.command == command)
    if m.result != mavutil.mavlink.MAV_RESULT_ACCEPTED:
        sys.exit(f"command {command} refused: {m.result}")

master = mavutil.mavlink_connection(sys.argv[1])
master.wait_heartbeat(timeout=10)
print("heartbeat", master.flightmode, flush=True)
master.set_mode("GUIDED")
ack(master, mavutil.mavlink.MAV_CMD_DO_SET_MODE)
master.arducopter_arm()
ack(master, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
master.motors_armed_wait()
master.mav.command_long_send(master.target_system, master.target_component,
                             mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 1.0)
ack(master, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF)
wait(master, "LOCAL_POSITION_NED", lambda m: m.z < -0.95, timeout=15)
print("at 1 m", flush=True)
start = latest(master)
for _ in range(40):  # 2 s north at 0.5 m/s, 20 Hz
    master.mav.set_position_target_local_ned_send(
        0, master.target_system, master.target_component, mavutil.mavlink.MAV_FRAME_LOCAL_NED,
        0b0000_1101_1100_0111, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0)
    time.sleep(0.05)
moved = latest(master).x - start.x
print(f"moved {moved:.2f} m north", flush=True)
master.set_mode("LAND")
ack(master, mavutil.mavlink.MAV_CMD_DO_SET_MODE)
end = time.time() + 20
while master.motors_armed():
    if time.time() > end:
        sys.exit("still armed 20 s after LAND")
    master.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
print("disarmed", master.flightmode, flush=True)
"""

# The PX4 offboard recipe (PX4 user guide "Offboard Control from Linux", MAVSDK's offboard example): arm, take
# off, then stream setpoints before asking for OFFBOARD, which PX4 refuses without them.
PX4_SCRIPT = """
import math, sys, time
from pymavlink import mavutil

def wait(conn, kind, cond=lambda m: True, timeout=10.0):
    end = time.time() + timeout
    while time.time() < end:
        m = conn.recv_match(type=kind, blocking=True, timeout=0.5)
        if m is not None and cond(m):
            return m
    sys.exit(f"timed out waiting for {kind}")

def latest(conn):
    # the newest LOCAL_POSITION_NED: read what queued up while the script was busy
    while conn.recv_match(blocking=False) is not None:
        pass
    return conn.messages["LOCAL_POSITION_NED"]

def result(conn, command):
    return wait(conn, "COMMAND_ACK", lambda m: m.command == command).result

def setpoint(conn, vx):
    conn.mav.set_position_target_local_ned_send(0, conn.target_system, conn.target_component,
                                                mavutil.mavlink.MAV_FRAME_LOCAL_NED, 0b0000_1101_1100_0111,
                                                0, 0, 0, vx, 0, 0, 0, 0, 0, 0, 0)

OK = mavutil.mavlink.MAV_RESULT_ACCEPTED
master = mavutil.mavlink_connection(sys.argv[1])
master.wait_heartbeat(timeout=10)
print("heartbeat", master.flightmode, flush=True)
master.arducopter_arm()  # the same COMPONENT_ARM_DISARM for any autopilot
assert result(master, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == OK
master.mav.command_long_send(master.target_system, master.target_component, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF,
                             0, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
assert result(master, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF) == OK
wait(master, "LOCAL_POSITION_NED", lambda m: m.z < -2.4, timeout=15)  # MIS_TAKEOFF_ALT 2.5 m
master.set_mode("OFFBOARD")
print("offboard without a stream:", result(master, mavutil.mavlink.MAV_CMD_DO_SET_MODE), flush=True)
for _ in range(10):
    setpoint(master, 0.0)
    time.sleep(0.05)
master.set_mode("OFFBOARD")
assert result(master, mavutil.mavlink.MAV_CMD_DO_SET_MODE) == OK
start = latest(master)
for _ in range(40):
    setpoint(master, 0.5)
    time.sleep(0.05)
print(f"moved {latest(master).x - start.x:.2f} m north", flush=True)
master.set_mode("LAND")
assert result(master, mavutil.mavlink.MAV_CMD_DO_SET_MODE) == OK
end = time.time() + 20
while master.motors_armed():
    if time.time() > end:
        sys.exit("still armed 20 s after LAND")
    master.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
print("disarmed", master.flightmode, flush=True)
"""


def _run_script(script: str, autopilot: Autopilot) -> tuple[list[str], MavlinkVehicle]:
    port = free_base_port(1)
    vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", VehicleConfig(autopilot=autopilot), seed=1).start()
    try:
        proc = subprocess.run([sys.executable, "-c", textwrap.dedent(script), f"udpin:127.0.0.1:{port}"],
                              capture_output=True, text=True, timeout=90)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        return proc.stdout.splitlines(), vehicle
    finally:
        vehicle.stop()


def test_an_ordinary_arducopter_guided_script_flies_it_and_ends_disarmed():
    lines, vehicle = _run_script(ARDUCOPTER_SCRIPT, Autopilot.ARDUPILOT)
    assert lines[0] == "heartbeat STABILIZE"  # mavutil decoded the ArduCopter mode from the heartbeat
    assert lines[1] == "at 1 m"
    moved = float(lines[2].split()[1])
    assert 0.6 < moved < 1.3  # 2 s at 0.5 m/s, with the vehicle's acceleration limit
    assert lines[3] == "disarmed LAND"
    assert not vehicle.armed and vehicle.position[2] == 0.0 and vehicle.ignored_setpoints == 0


def test_an_ordinary_px4_offboard_script_flies_it_and_ends_disarmed():
    lines, vehicle = _run_script(PX4_SCRIPT, Autopilot.PX4)
    assert lines[0] == "heartbeat LOITER"  # PX4 Hold, by mavutil's decoding of px4_custom_mode
    assert lines[1] == "offboard without a stream: 1"  # MAV_RESULT_TEMPORARILY_REJECTED
    assert 0.6 < float(lines[2].split()[1]) < 1.3
    assert lines[3] == "disarmed LAND"
    assert not vehicle.armed and vehicle.position[2] == 0.0


# ---- mode encodings ----------------------------------------------------------------------------------

def test_px4_custom_mode_is_the_union_of_px4_custom_mode_h_and_names_match_pymavlink():
    from pymavlink import mavutil
    assert px4_custom_mode(6) == 393216  # OFFBOARD: main mode 6 in the third byte
    assert px4_split(px4_custom_mode(PX4_MAIN_AUTO, PX4_SUB_LOITER)) == (4, 3)
    for name, (_, main, sub) in mavutil.px4_map.items():
        if name in ("POSCTL", "OFFBOARD", "TAKEOFF", "LOITER", "RTL", "LAND"):
            custom = px4_custom_mode(main, sub)
            assert mode_name(Autopilot.PX4, custom) == name == mavutil.interpret_px4_mode(0, custom)
    for number, name in mavutil.mode_mapping_acm.items():
        if name in ("STABILIZE", "GUIDED", "LOITER", "RTL", "LAND", "BRAKE"):
            assert mode_name(Autopilot.ARDUPILOT, number) == name


# ---- firmware rules, one at a time ---------------------------------------------------------------

@pytest.fixture(params=[Autopilot.ARDUPILOT, Autopilot.PX4], ids=["ardupilot", "px4"])
def pair(request):
    port = free_base_port(1)
    with MavlinkVehicle(f"udpout:127.0.0.1:{port}", VehicleConfig(autopilot=request.param), seed=2) as vehicle:
        link = open_link(f"mavlink:udpin:127.0.0.1:{port}", connect_timeout=5.0)
        try:
            yield vehicle, link
        finally:
            link.close()


def test_takeoff_only_where_the_firmware_allows_it(pair):
    vehicle, link = pair
    mav = link._mav
    if link.autopilot is Autopilot.ARDUPILOT:
        link.arm()  # STABILIZE allows arming...
        result = link.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.0)
        assert result == mav.MAV_RESULT_FAILED  # ...but has no user takeoff: only GUIDED does
        link.disarm()
    link.set_mode("LAND")
    with pytest.raises(LinkError, match="arming refused"):  # LAND is not an armable mode on either
        link.arm()
    assert not vehicle.armed


def test_the_set_mode_message_changes_the_mode_too(pair):
    vehicle, link = pair
    mav = link._mav
    custom = 5 if link.autopilot is Autopilot.ARDUPILOT else px4_custom_mode(3)  # LOITER / POSCTL
    link._send("set_mode_send", link.target_system, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom)
    assert _wait(lambda: link.mode == ("LOITER" if link.autopilot is Autopilot.ARDUPILOT else "POSCTL"), 2.0)


def test_arming_is_refused_outside_the_vehicles_fence(pair):
    vehicle, link = pair
    from groundstation.safety import FenceConfig
    link.upload_fence(FenceConfig(box=(1.0, 3.0, 1.0, 3.0), z_min=0.2, z_max=1.5, margin=0.2))  # (0, 0) is out
    with pytest.raises(LinkError, match="arming refused"):  # ArduCopter "vehicle outside fence"; PX4 geofence
        link.arm()
    link.clear_fence()
    link.arm()
    assert _wait(lambda: link.armed, 2.0)
    link.disarm()


def test_a_takeoff_asked_again_while_under_way_is_not_sent_and_a_new_flight_takes_off_again(pair):
    """The flight supervisor re-sends a takeoff whose vehicle still reports itself on the ground (the landed state
    lags the ack); the firmware would refuse a second NAV_TAKEOFF while climbing, so the link sends none and
    logs no refusal. After the landing and disarm, the next takeoff is sent and flown, on both firmwares."""
    vehicle, link = pair
    link.takeoff(0.5, 1.0).result(timeout=5.0)
    again = link.takeoff(0.5, 1.0)
    assert again.done() and again.result() is None
    assert link.command_errors == []
    assert _wait(lambda: vehicle.position[2] > 0.3, 5.0)  # the first takeoff flies on
    link.land(1.0).result(timeout=5.0)
    assert _wait(lambda: not vehicle.armed, 8.0) and _wait(lambda: not link.armed, 2.0)
    # a new flight: sent, accepted (a PX4 vehicle stays in LAND after landing, and does not arm there: the link
    # switches it to HOLD first)
    link.takeoff(0.4, 1.0).result(timeout=5.0)
    assert _wait(lambda: vehicle.armed and vehicle.position[2] > 0.2, 5.0)
    assert link.command_errors == []
    link.land(1.0).result(timeout=5.0)
    assert _wait(lambda: not vehicle.armed, 8.0)


def test_setpoints_move_it_only_in_guided_or_offboard(pair):
    vehicle, link = pair
    link.takeoff(0.5, 1.0).result(timeout=5.0)
    assert _wait(lambda: vehicle.mode is VehicleMode.HOLD, 4.0)
    link.set_mode("LOITER")
    assert _wait(lambda: link.mode == "LOITER", 1.0)
    before, ignored = vehicle.position, vehicle.ignored_setpoints
    _stream(lambda: link.send_velocity(0.5, 0.0, 0.0), 0.6)
    assert vehicle.ignored_setpoints > ignored + 10
    assert np.linalg.norm(vehicle.position[:2] - before[:2]) < 0.05  # it held: LOITER ignores setpoints
    if link.autopilot is Autopilot.ARDUPILOT:
        link.set_mode("GUIDED")
    else:
        _stream(lambda: link.send_velocity(0.0, 0.0, 0.0), 0.3)  # PX4 takes OFFBOARD only with a stream
        link.set_mode("OFFBOARD")
    assert stream_until(lambda: link.send_velocity(0.5, 0.0, 0.0), lambda: vehicle.position[0] - before[0] > 0.15,
                        5.0)
    assert link.mode in ("GUIDED", "OFFBOARD")
    link.land(1.0).result(timeout=5.0)
    assert _wait(lambda: not vehicle.armed, 8.0)


def test_rtl_climbs_no_higher_than_the_fence_allows_returns_home_and_lands(pair):
    vehicle, link = pair
    from groundstation.safety import FenceConfig
    link.upload_fence(FenceConfig(box=(-2.0, 2.0, -2.0, 2.0), z_min=0.2, z_max=1.5, margin=0.2))
    if link.autopilot is Autopilot.ARDUPILOT:
        link.set_param("FENCE_MARGIN", 0.5)  # return altitude = ceiling - margin
    else:
        link.set_param("RTL_RETURN_ALT", 1.0)
    link.takeoff(0.5, 1.0).result(timeout=5.0)
    assert _wait(lambda: vehicle.mode is VehicleMode.HOLD, 4.0)
    assert stream_until(lambda: link.send_position(1.0, 0.8, 0.5),
                        lambda: np.allclose(vehicle.position[:2], (1.0, 0.8), atol=0.1), 8.0)
    link.command(link._mav.MAV_CMD_NAV_RETURN_TO_LAUNCH)
    assert _wait(lambda: vehicle.position[2] > 0.95, 4.0)
    peak = [0.0]

    def home_and_down() -> bool:
        peak[0] = max(peak[0], vehicle.position[2])
        return not vehicle.armed
    assert _wait(home_and_down, 15.0)
    assert peak[0] < 1.1 and vehicle.fence_breaches == 0
    assert np.allclose(vehicle.position, (0.0, 0.0, 0.0), atol=0.08)


def test_px4_offboard_needs_a_stream_and_its_loss_lands_the_vehicle():
    port = free_base_port(1)
    with MavlinkVehicle(f"udpout:127.0.0.1:{port}", VehicleConfig(autopilot=Autopilot.PX4), seed=4) as vehicle:
        with open_link(f"mavlink:udpin:127.0.0.1:{port}", connect_timeout=5.0) as link:
            assert vehicle.params["COM_OBL_RC_ACT"] == 4  # the link chose "land" for the offboard loss
            link.takeoff(0.6, 1.0).result(timeout=5.0)
            assert _wait(lambda: vehicle.mode is VehicleMode.HOLD and link.mode == "LOITER", 4.0)
            with pytest.raises(LinkError, match="mode OFFBOARD refused: MAV_RESULT_TEMPORARILY_REJECTED"):
                link.set_mode("OFFBOARD")  # no setpoint within COM_OF_LOSS_T
            sent: list[float] = []
            _stream(lambda: (link.send_velocity(0.0, 0.0, 0.0), sent.append(time.monotonic())), 0.8)
            assert link.mode == "OFFBOARD"  # the link asked for it once the stream had run offboard_prestream
            # the loss counts from the last setpoint sent, not from when this thread ran again (a loaded machine
            # can hold it back for a few hundred ms after that send: measured 0.35 s under stress-ng --cpu 2)
            t_stop = sent[-1]
            assert _wait(lambda: vehicle.flight_mode == "LAND", 3.0)
            assert vehicle.params["COM_OF_LOSS_T"] - 0.1 < time.monotonic() - t_stop < 2.0
            assert _wait(lambda: not vehicle.armed, 8.0)  # AUTO.LAND, then COM_DISARM_LAND
            assert vehicle.failsafe_landings == 1
            assert link.wait_telemetry(1.0, lambda s: s.flight_state is FlightState.DISARMED)


# ---- the link never waits on the caller's thread -------------------------------------------------

def test_land_returns_at_once_and_a_silent_vehicle_fails_its_future_with_a_clear_error(pair):
    vehicle, link = pair
    link.takeoff(0.4, 0.5).result(timeout=5.0)
    assert _wait(lambda: vehicle.mode is VehicleMode.HOLD, 4.0)
    vehicle.kill_link()
    t0 = time.monotonic()
    first = link.land(1.0)
    again = link.land(1.0)  # the supervisor repeats land commands: they share the one in flight
    assert time.monotonic() - t0 < 0.05 and again is first
    with pytest.raises(LinkError, match="unanswered after 4 tries"):
        first.result(timeout=10.0)
    assert any("land" in e for e in link.command_errors)
    # the vehicle is on its own: its GCS-loss failsafe brings it down (ArduCopter after a 4 s pause)
    assert _wait(lambda: not vehicle.armed, 15.0)
