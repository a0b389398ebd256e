"""MavlinkLink (pymavlink) against the simulated MAVLink vehicle over UDP loopback: both sides are real
pymavlink peers; nothing is mocked."""
from __future__ import annotations

import functools
import math
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from flight_fixtures import stream as _stream, stream_until, wait_until  # noqa: E402
from groundstation.link import FlightState, LinkError, open_link, scheme_of  # noqa: E402
from groundstation.mavlink_autopilot import Autopilot, fence_items  # noqa: E402
from groundstation.mavlink_link import (MavlinkLink, enu_to_ned, ned_to_enu, parse_uri, split_baud,  # noqa: E402
                                        yaw_enu_to_ned, yaw_ned_to_enu)
from groundstation.safety import FenceConfig, KeepOut  # noqa: E402
from groundstation.sim.mavlink_vehicle import LAND_PAUSE, MavlinkVehicle, VehicleConfig, VehicleMode  # noqa: E402
from groundstation.sim.swarm import free_base_port  # noqa: E402

START = (0.5, -0.3, 0.0)


_wait = functools.partial(wait_until, period=0.01)


@pytest.fixture
def pair():
    """(vehicle, link): the vehicle sends to the port the link listens on (udpout -> udpin)."""
    port = free_base_port(1)
    config = VehicleConfig(params={"GUID_TIMEOUT": 0.5})
    with MavlinkVehicle(f"udpout:127.0.0.1:{port}", config, start=START, seed=3) as vehicle:
        link = open_link(f"mavlink:udpin:127.0.0.1:{port}", connect_timeout=5.0)
        try:
            yield vehicle, link
        finally:
            link.close()


# ---- URIs and frames ------------------------------------------------------------------------------

def test_uri_form_is_its_own_scheme_and_malformed_ones_are_named():
    assert scheme_of("mavlink:udpin:127.0.0.1:14550") == "mavlink"
    assert scheme_of("udp://127.0.0.1:19850") == "udp"  # stays cflib's
    assert parse_uri("mavlink:udpin:127.0.0.1:14550") == "udpin:127.0.0.1:14550"
    assert parse_uri("mavlink:/dev/ttyACM0,57600") == "/dev/ttyACM0,57600"
    assert split_baud("/dev/ttyACM0,57600") == ("/dev/ttyACM0", 57600)
    assert split_baud("/dev/ttyUSB0") == ("/dev/ttyUSB0", 115200)
    assert split_baud("udpin:127.0.0.1:14550") == ("udpin:127.0.0.1:14550", 115200)
    with pytest.raises(LinkError, match="after a comma: mavlink:/dev/ttyACM0,57600"):
        parse_uri("mavlink:/dev/ttyACM0:57600")
    for bad, needle in (("mavlink:", "missing"), ("mavlink://127.0.0.1:14550", "no '//'"),
                        ("mavlink:udpin:14550", "HOST:PORT"), ("udp://1.2.3.4:5", "not a MAVLink URI")):
        with pytest.raises(LinkError, match=needle):
            parse_uri(bad)
    with pytest.raises(LinkError, match="period_ms"):
        MavlinkLink("mavlink:udpin:127.0.0.1:1", period_ms=0)


def test_frames_round_trip_and_match_the_conventions():
    rng = np.random.default_rng(0)
    for v in rng.normal(size=(50, 3)):
        assert np.allclose(ned_to_enu(*enu_to_ned(*v)), v)
    assert enu_to_ned(1.0, 2.0, 3.0) == (2.0, 1.0, -3.0)  # east, north, up -> north, east, down
    assert yaw_enu_to_ned(0.0) == pytest.approx(math.pi / 2)  # facing east
    assert yaw_enu_to_ned(math.pi / 2) == pytest.approx(0.0)  # facing north
    for yaw in rng.uniform(-math.pi, math.pi, 20):
        assert math.cos(yaw_ned_to_enu(yaw_enu_to_ned(yaw)) - yaw) == pytest.approx(1.0)


def test_no_vehicle_is_a_named_error_within_the_timeout():
    port = free_base_port(1)
    t0 = time.monotonic()
    with pytest.raises(LinkError, match="no vehicle heartbeat"):
        MavlinkLink(f"mavlink:udpin:127.0.0.1:{port}", connect_timeout=0.3)
    assert time.monotonic() - t0 < 1.5


# ---- the vehicle through the link (ArduCopter personality) ----------------------------------------

def test_heartbeat_and_local_position_telemetry(pair):
    vehicle, link = pair
    assert link.target_system == 1 and not link.armed
    assert link.autopilot is Autopilot.ARDUPILOT and link.mode == "STABILIZE"  # ArduCopter boots in STABILIZE
    o, want = link.origin, vehicle.config.origin  # GPS_GLOBAL_ORIGIN on request
    assert (o.lat, o.lon, o.alt) == pytest.approx((want.lat, want.lon, want.alt), abs=1e-6)
    t0 = link.telemetry()
    time.sleep(0.5)
    t1 = link.wait_telemetry(1.0, lambda s: s.battery > 0)
    assert np.allclose(t1.position, START, atol=0.15)  # NED on the wire, ENU here; LPS-like noise
    assert abs(t1.velocity[2]) < 0.1 and 3.9 < t1.battery <= 4.2
    assert t1.flight_state is FlightState.DISARMED
    assert t1.vehicle_time_ms > t0.vehicle_time_ms and t1.t > t0.t
    # the 50 Hz stream asked for with SET_MESSAGE_INTERVAL: what the vehicle took (the rate it achieves is the
    # machine's: a loaded one delivers fewer, never more)
    assert vehicle._intervals[link._mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED] == pytest.approx(0.02)
    rate = (link.stats().telemetry_received - 1) / (t1.t - link._opened_at)
    assert 0.0 < rate < 60.0
    assert t1.link_quality > 0.8
    # the link turned on the firmware's GCS failsafe (off by default) with its own timeout
    assert vehicle.params["FS_GCS_ENABLE"] == 5 and vehicle.params["FS_GCS_TIMEOUT"] == 1.0
    assert math.isfinite(vehicle._last_gcs)  # the link's heartbeats reach the vehicle


def test_setpoints_outside_guided_are_ignored_and_takeoff_sets_guided(pair):
    # Flying it with setpoints, through both frames, is in tests/test_link_contract.py.
    vehicle, link = pair
    _stream(lambda: link.send_velocity(0.5, 0.0, 0.0), 0.1)
    assert vehicle.ignored_setpoints > 0 and vehicle.mode is VehicleMode.DISARMED  # STABILIZE: ignored
    assert np.allclose(vehicle.velocity, 0.0)
    link.takeoff(0.4, 0.5).result(timeout=5.0)
    assert vehicle.flight_mode == "GUIDED" and vehicle.armed
    assert link.wait_telemetry(1.0, lambda s: s.flight_state is FlightState.FLYING)
    assert _wait(lambda: vehicle.mode is VehicleMode.HOLD, 3.0)
    assert vehicle.position[2] == pytest.approx(0.4, abs=0.06)
    assert stream_until(lambda: link.send_velocity(0.0, 0.5, 0.0), lambda: vehicle.velocity[1] > 0.3, 3.0)
    assert vehicle.mode is VehicleMode.VELOCITY  # north is +y
    t_last = time.monotonic()
    # GUID_TIMEOUT (0.5 s in this fixture, 3 s by default): the stale velocity target becomes a stop
    assert _wait(lambda: vehicle.mode is VehicleMode.HOLD, 2.0)
    assert time.monotonic() - t_last > 0.4
    link.land(0.4).result(timeout=5.0)
    assert vehicle.flight_mode == "LAND"
    assert _wait(lambda: vehicle.mode is VehicleMode.DISARMED, 3.0)  # LAND disarms on touchdown
    assert link.wait_telemetry(1.0, lambda s: s.flight_state is FlightState.DISARMED)


def test_fence_goes_up_as_global_items_and_params_and_a_breach_lands(pair):
    vehicle, link = pair
    fence = FenceConfig(box=(-1.0, 1.5, -1.0, 1.0), z_min=0.2, z_max=1.2, margin=0.2,
                        keep_out=(KeepOut(1.0, 0.5, 0.2),))
    items = fence_items(fence, link.origin)
    assert link.upload_fence(fence) == len(items) == 5
    assert all(abs(it["x"]) > 1e8 for it in items)  # latitude x 1e7, not metres
    vf = vehicle.fence
    assert vf is not None and len(vf.circles) == 1
    assert vf.circles[0] == pytest.approx((1.0, 0.5, 0.2), abs=0.02)  # 1e-7 degree is about 1 cm
    assert np.allclose(np.sort(vf.polygon, axis=0), np.sort(fence.polygon, axis=0), atol=0.02)
    assert vehicle.params["FENCE_ENABLE"] == 1 and vehicle.params["FENCE_ACTION"] == 2
    assert vehicle.fence_ceiling == pytest.approx(1.2, rel=1e-6)  # FENCE_ALT_MAX, float32 on the wire
    assert vf.contains(np.array([0.0, 0.0, 1.0])) and not vf.contains(np.array([1.0, 0.55, 1.0]))
    assert not vf.contains(np.array([2.0, 0.0, 1.0]))
    link.takeoff(0.4, 0.5).result(timeout=5.0)
    assert _wait(lambda: vehicle.mode is VehicleMode.HOLD, 3.0)
    # The vehicle's fence is the backstop behind the ground station's geofence: sent straight through the
    # raw link, a target past the ceiling makes the vehicle land on its own (FENCE_ACTION 2).
    _stream(lambda: link.send_position(START[0], START[1], 1.6), 1.2)
    assert vehicle.fence_breaches >= 1 and vehicle.position[2] < 1.4  # breach at 1.2 m + stopping distance
    assert vehicle.flight_mode == "LAND" and vehicle.mode is VehicleMode.LAND
    assert _wait(lambda: vehicle.velocity[2] < -0.3, 1.0)  # descending; setpoints no longer obeyed
    link.clear_fence()
    assert vehicle.fence is None and vehicle.params["FENCE_ENABLE"] == 0


def test_gcs_failsafe_lands_after_the_firmware_pause_and_disarms(pair):
    vehicle, link = pair
    link.takeoff(0.3, 0.4).result(timeout=5.0)
    assert _wait(lambda: vehicle.mode is VehicleMode.HOLD, 3.0)
    t_close = time.monotonic()
    link.close()  # no more GCS heartbeats
    assert _wait(lambda: vehicle.flight_mode == "LAND", 2.5)
    # FS_GCS_TIMEOUT (1 s) counted from the last heartbeat, up to one heartbeat period before the close
    assert 1.0 - link.heartbeat_period - 0.05 < time.monotonic() - t_close < 2.0
    z0 = vehicle.position[2]
    assert not _wait(lambda: vehicle.position[2] < z0 - 0.1, LAND_PAUSE - 0.5)  # LAND_WITH_DELAY_MS: it waits
    assert _wait(lambda: vehicle.mode is VehicleMode.DISARMED, LAND_PAUSE + 3.0)
    assert _wait(lambda: vehicle.position[2] == 0.0, 0.3)
    assert vehicle.failsafe_landings == 1


def test_emergency_stop_disarms_and_the_link_keeps_it_locked_until_reboot(pair):
    vehicle, link = pair
    link.takeoff(0.4, 0.5).result(timeout=5.0)
    assert _wait(lambda: vehicle.mode is VehicleMode.HOLD, 3.0)
    link.emergency_stop()
    assert _wait(lambda: vehicle.mode is VehicleMode.DISARMED, 0.3)  # ArduCopter: termination is a disarm
    assert _wait(lambda: vehicle.position[2] == 0.0, 1.0)  # motors off: it falls
    assert link.wait_telemetry(1.0, lambda s: s.flight_state is FlightState.LOCKED)
    with pytest.raises(LinkError, match="locked"):
        link.takeoff(0.5, 1.0)
    result = link.command(link._mav.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
    assert result == link._mav.MAV_RESULT_ACCEPTED
    assert link.wait_telemetry(1.0, lambda s: s.flight_state is FlightState.DISARMED)


def test_disarm_in_the_air_is_refused_unless_forced(pair):
    vehicle, link = pair
    link.takeoff(0.4, 0.6).result(timeout=5.0)
    assert _wait(lambda: vehicle.mode is VehicleMode.HOLD, 3.0)
    with pytest.raises(LinkError, match="disarming refused: MAV_RESULT_FAILED"):
        link.disarm()
    link.disarm(force=True)
    assert _wait(lambda: vehicle.position[2] == 0.0, 1.0)


def test_swarm_gs_sim_serves_mavlink_vehicles():
    port = free_base_port(2)
    proc = subprocess.Popen([sys.executable, "-m", "groundstation.cli", "sim", "--drones", "0", "--mavlink", "2",
                             "--mavlink-port", str(port), "--duration", "20"], stdout=subprocess.PIPE, text=True)
    try:
        lines = [proc.stdout.readline() for _ in range(3)]
        assert "2 simulated MAVLink vehicles" in lines[0]
        uri = lines[2].strip()
        assert uri == f"mavlink:udpin:127.0.0.1:{port + 1}"
        with open_link(uri, connect_timeout=5.0) as link:
            assert link.target_system == 2 and link.telemetry().flight_state is FlightState.DISARMED
    finally:
        proc.terminate()
        assert proc.wait(timeout=5) == 0
