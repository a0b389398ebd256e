"""The simulated Crazyflie, driven by unmodified cflib over UDP (never a mock of cflib)."""
from __future__ import annotations

import functools
import socket
import struct
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest

cflib = pytest.importorskip("cflib")

import cflib.crtp  # noqa: E402
from cflib.crazyflie import Crazyflie  # noqa: E402
from cflib.crazyflie.log import LogConfig  # noqa: E402
from cflib.crazyflie.swarm import CachedCfFactory, Swarm  # noqa: E402
from cflib.crazyflie.syncCrazyflie import SyncCrazyflie  # noqa: E402
from cflib.crazyflie.syncLogger import SyncLogger  # noqa: E402

from flight_fixtures import stream as _stream, wait_until  # noqa: E402
from groundstation.sim import crtp  # noqa: E402
from groundstation.sim.firmware import Firmware, Mode, SupervisorState  # noqa: E402
from groundstation.sim.flight_model import QuadBatch, QuadParams  # noqa: E402
from groundstation.sim.swarm import SimError, SimSwarm, free_base_port  # noqa: E402

cflib.crtp.init_drivers()


@pytest.fixture
def sims(request):
    n = getattr(request, "param", 1)
    with SimSwarm(n, base_port=free_base_port(n), seed=7) as swarm:
        yield swarm


def _connect(uri: str, tmp_path=None) -> SyncCrazyflie:
    cf = Crazyflie(rw_cache=str(tmp_path) if tmp_path else None)
    scf = SyncCrazyflie(uri, cf=cf)
    scf.open_link()
    return scf


_wait = functools.partial(wait_until, period=0.02)


def _first_log(scf: SyncCrazyflie, names: list[str], period_ms: int = 10) -> dict:
    config = LogConfig("probe", period_ms)
    for name in names:
        config.add_variable(name, "float")
    with SyncLogger(scf, config) as logger:
        for _, data, _ in logger:
            return data


# ---- raw protocol --------------------------------------------------------------------------------

def _raw(port: int, datagram: bytes) -> bytes:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(1.0)
        s.connect(("127.0.0.1", port))
        s.send(datagram)
        return s.recv(64)


def test_link_echo_source_version_and_scan_probe(sims):
    port = sims.base_port
    assert _raw(port, bytes((crtp.header(15, 0),)) + b"ping") == bytes((0xF0,)) + b"ping"
    source = _raw(port, bytes((crtp.header(15, 1), 0)))
    assert source[1:19] == b"Bitcraze Crazyflie" and len(source) == 31
    assert _raw(port, bytes((crtp.header(13, 1), 0))) == bytes((0xD1, 0, crtp.PROTOCOL_VERSION))
    assert _raw(port, bytes((crtp.header(13, 1), 1)))[2:].decode() == crtp.FIRMWARE_VERSION
    assert _raw(port, b"\xff")[0] == 0xF3  # the UDP driver's scan probe gets an answer


def test_supervisor_answers_single_bit_queries_like_crtp_supervisor_c(sims):
    port, h = sims.base_port, crtp.header(crtp.Port.SUPERVISOR, 0)
    assert _raw(port, bytes((h, 0x02))) == bytes((h, 0x82, 1))  # CMD_IS_ARMED: auto-armed
    assert _raw(port, bytes((h, 0x07))) == bytes((h, 0x87, 0))  # CMD_IS_LOCKED
    info = struct.unpack("<H", _raw(port, bytes((h, 0x0C)))[2:])[0]
    assert all(_raw(port, bytes((h, c)))[2] == (info >> (c - 1)) & 1 for c in range(1, 12))


def test_malformed_packets_are_dropped_and_the_server_keeps_answering(sims):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.connect(("127.0.0.1", sims.base_port))
        for junk in (b"\x70\x07\x01", b"\x80\x07", b"\x20\x01", b"\x50\x01\x06\x01\x07", b"\x90"):
            s.send(junk)
    assert _raw(sims.base_port, b"\xf0ok") == b"\xf0ok"


def test_busy_port_is_a_named_error(sims):
    with pytest.raises(SimError, match="the port is taken .*--base-port"):
        SimSwarm(1, base_port=sims.base_port).start()


# ---- cflib end to end ----------------------------------------------------------------------------

def test_cflib_connects_reads_tocs_and_params(sims, tmp_path):
    scf = _connect(sims.uris[0], tmp_path)
    try:
        cf = scf.cf
        assert cf.platform.get_protocol_version() == crtp.PROTOCOL_VERSION
        names = {f"{g}.{n}" for g, group in cf.log.toc.toc.items() for n in group}
        for required in ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z", "stateEstimate.vx",
                         "stateEstimate.vy", "stateEstimate.vz", "pm.vbat", "radio.rssi", "kalman.varPX",
                         "kalman.varPY", "kalman.varPZ", "supervisor.info"):
            assert required in names
        assert cf.log.toc.get_element_by_complete_name("supervisor.info").ctype == "uint16_t"
        scf.wait_for_params()
        assert cf.param.get_value("stabilizer.estimator") == "2"
        assert float(cf.param.get_value("hlCommander.vland")) == pytest.approx(0.2)
        assert cf.mem.nbr_of_mems == 0
        with pytest.raises(AttributeError, match="read-only"):
            cf.param.set_value("deck.bcLoco", 0)
        data = _first_log(scf, ["pm.vbat", "stateEstimate.z"])
        assert 3.9 < data["pm.vbat"] <= 4.2 and abs(data["stateEstimate.z"]) < 0.2
        assert cf.supervisor.read_state_list() == ["Is armed", "Is auto armed", "Can fly",
                                                   "Finished HL trajectory"]  # planner idle, no trajectory yet
    finally:
        scf.close_link()
    # The TOCs were cached by CRC: a second connection reads them from the cache.
    assert list(tmp_path.glob("*.json"))
    scf = _connect(sims.uris[0], tmp_path)
    scf.close_link()


def test_reset_estimation_param_write_restarts_the_estimator(sims):
    with SyncCrazyflie(sims.uris[0], cf=Crazyflie()) as scf:
        scf.wait_for_params()
        config = LogConfig("var", 10)
        config.add_variable("kalman.varPX", "float")
        with SyncLogger(scf, config) as logger:
            before = next(iter(logger))[1]["kalman.varPX"]
            scf.cf.param.set_value("kalman.resetEstimation", "1")
            # the reset sets the variance to MAX_COVARIANCE; the next measurements pull it down within
            # tens of milliseconds, so the samples right after it are well above the converged value
            peak = 0.0
            for _, data, _ in logger:
                peak = max(peak, data["kalman.varPX"])
                if scf.cf.param.get_value("kalman.resetEstimation") == "1":  # echoed write
                    break
            for k, (_, data, _) in enumerate(logger):
                peak = max(peak, data["kalman.varPX"])
                if k >= 5:
                    break
        assert before < 0.002 and peak > 0.005
        assert _wait(lambda: _first_log(scf, ["kalman.varPX"])["kalman.varPX"] < 0.002, 3.0)
        assert sims.param(0, "kalman.resetEstimation") == 0  # the estimator cleared its flag


def test_high_level_commander_takes_off_goes_to_and_lands(sims):
    with SyncCrazyflie(sims.uris[0], cf=Crazyflie()) as scf:
        hl = scf.cf.high_level_commander
        hl.takeoff(0.5, 1.2)  # within the model's limits: peak 0.9 m/s, 2.6 m/s^2
        time.sleep(1.4)
        assert sims.truth(0).position[2] == pytest.approx(0.5, abs=0.03)
        assert "Is flying" in scf.cf.supervisor.read_state_list()
        hl.go_to(1.0, 0.5, 0.8, 0.0, 1.5)
        time.sleep(1.8)
        assert np.allclose(sims.truth(0).position, (1.0, 0.5, 0.8), atol=0.05)
        est = _first_log(scf, ["stateEstimate.x", "stateEstimate.y", "stateEstimate.z"])
        assert np.allclose(list(est.values()), (1.0, 0.5, 0.8), atol=0.2)  # LPS-like noise, a few cm
        time.sleep(0.7)  # the planner holds its last target without further commands (no watchdog)
        assert np.allclose(sims.truth(0).position, (1.0, 0.5, 0.8), atol=0.05)
        assert sims.truth(0).supervisor == "flying"
        hl.land(0.0, 1.2)
        # the landing ends with the planner idle (motors off); "landed" once idle for 2 s (supervisor.c)
        assert _wait(lambda: sims.truth(0).supervisor == "landed", 6.0)
        truth = sims.truth(0)
        assert truth.position[2] == 0.0 and not truth.motors_on


def test_streamed_setpoints_then_the_watchdog_levels_out_and_locks(sims):
    with SyncCrazyflie(sims.uris[0], cf=Crazyflie()) as scf:
        commander = scf.cf.commander
        x0, y0, _ = sims.truth(0).position
        _stream(lambda: commander.send_position_setpoint(x0, y0, 0.5, 0.0), 1.2)
        assert sims.truth(0).position[2] == pytest.approx(0.5, abs=0.05)
        _stream(lambda: commander.send_velocity_world_setpoint(0.4, 0.0, 0.0, 0.0), 0.5)
        assert sims.truth(0).velocity[0] == pytest.approx(0.4, abs=0.08)
        _stream(lambda: commander.send_hover_setpoint(0.0, 0.0, 0.0, 0.7), 0.8)
        assert sims.truth(0).position[2] == pytest.approx(0.7, abs=0.05)
        t_last = time.monotonic()
        time.sleep(0.8)  # > 0.5 s: level out and hold the height
        truth = sims.truth(0)
        assert truth.supervisor == "level_out" and truth.motors_on
        assert truth.position[2] == pytest.approx(0.7, abs=0.06)
        assert _wait(lambda: sims.is_locked(0), 2.5 - (time.monotonic() - t_last))
        assert time.monotonic() - t_last > 1.9  # ... and at 2 s motors off, locked
        assert _wait(lambda: sims.truth(0).position[2] == 0.0, 1.0)
        assert "Is locked" in scf.cf.supervisor.read_state_list()
        scf.cf.high_level_commander.takeoff(0.5, 1.0)  # a locked drone does not take off again
        time.sleep(0.3)
        assert sims.truth(0).position[2] == 0.0
    sims.reboot(0)
    assert sims.truth(0).supervisor == "ready"


def test_after_the_watchdog_a_levelled_drone_coasts_on_its_momentum(sims):
    """supervisorOverrideSetpoint: x and y control off in level-out, so the drone keeps its velocity (only
    drag slows it); z keeps the setpoint's mode (here a velocity of 0)."""
    with SyncCrazyflie(sims.uris[0], cf=Crazyflie()) as scf:
        commander = scf.cf.commander
        x0, y0, _ = sims.truth(0).position
        _stream(lambda: commander.send_position_setpoint(x0, y0, 0.6, 0.0), 1.2)
        _stream(lambda: commander.send_velocity_world_setpoint(0.5, 0.0, 0.0, 0.0), 0.6)
        t_last, x_last = time.monotonic(), sims.truth(0).position[0]
        assert _wait(lambda: sims.truth(0).supervisor == "level_out", 1.0)
        assert _wait(lambda: time.monotonic() - t_last > 1.2, 2.0)
        truth = sims.truth(0)
        assert truth.supervisor == "level_out"  # (unless the machine stalled past 2 s: then it is locked)
        assert 0.3 < truth.velocity[0] < 0.5  # coasting: slowed by drag alone, no brake
        assert truth.position[0] - x_last > 0.4
        assert truth.position[2] == pytest.approx(0.6, abs=0.1)
        assert _wait(lambda: sims.is_locked(0), 2.0)  # motors off at 2 s


def test_notify_setpoint_stop_hands_over_to_the_high_level_commander(sims):
    with SyncCrazyflie(sims.uris[0], cf=Crazyflie()) as scf:
        commander, hl = scf.cf.commander, scf.cf.high_level_commander
        x0, y0, _ = sims.truth(0).position
        _stream(lambda: commander.send_position_setpoint(x0, y0, 0.5, 0.0), 1.0)
        hl.go_to(x0, y0, 0.9, 0.0, 1.0)  # planned, but the streamed setpoint outranks the planner ...
        _stream(lambda: commander.send_position_setpoint(x0, y0, 0.5, 0.0), 0.3)  # ... and stops it
        assert sims.truth(0).position[2] == pytest.approx(0.5, abs=0.05)
        hl.land(0.0, 1.0)
        commander.send_notify_setpoint_stop(100)  # relax: the planner's landing is taken
        assert _wait(lambda: sims.truth(0).supervisor == "landed", 5.0)
        assert not sims.is_locked(0)


def test_a_land_without_the_hand_over_is_dropped_and_the_watchdog_locks(sims):
    with SyncCrazyflie(sims.uris[0], cf=Crazyflie()) as scf:
        commander, hl = scf.cf.commander, scf.cf.high_level_commander
        x0, y0, _ = sims.truth(0).position
        _stream(lambda: commander.send_position_setpoint(x0, y0, 0.5, 0.0), 1.0)
        t_last = time.monotonic()
        hl.land(0.0, 1.0)  # no notify-setpoint-stop: the streamed setpoint keeps priority and ages
        assert _wait(lambda: sims.truth(0).supervisor == "level_out", 1.0)
        assert sims.truth(0).position[2] == pytest.approx(0.5, abs=0.05)
        assert _wait(lambda: sims.is_locked(0), 3.0)
        assert time.monotonic() - t_last > 1.9


def test_stop_setpoint_cuts_the_motors_and_the_hand_over_avoids_the_lock(sims):
    with SyncCrazyflie(sims.uris[0], cf=Crazyflie()) as scf:
        scf.cf.high_level_commander.takeoff(0.3, 0.7)
        assert _wait(lambda: sims.truth(0).position[2] > 0.25, 2.0)
        # as cflib's examples do: the stop setpoint, then the hand-over so that the watchdog does not lock
        scf.cf.commander.send_stop_setpoint()
        scf.cf.commander.send_notify_setpoint_stop()
        assert _wait(lambda: sims.truth(0).position[2] == 0.0, 1.0)
        assert _wait(lambda: sims.truth(0).supervisor == "landed", 3.0)
        assert not sims.is_locked(0)
        scf.cf.high_level_commander.takeoff(0.3, 0.7)
        assert _wait(lambda: sims.truth(0).position[2] > 0.25, 2.0)
        scf.cf.commander.send_stop_setpoint()  # without the hand-over the stop setpoint ages: locked at 2 s
        assert _wait(lambda: sims.is_locked(0), 3.0)


def test_emergency_stops_lock_the_drone(sims):
    with SyncCrazyflie(sims.uris[0], cf=Crazyflie()) as scf:
        scf.cf.high_level_commander.takeoff(0.5, 0.8)
        time.sleep(1.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            scf.cf.loc.send_emergency_stop()  # cflib routes it to the supervisor port on protocol 12
        assert _wait(lambda: sims.is_locked(0), 0.5)
        assert _wait(lambda: sims.truth(0).position[2] == 0.0, 1.0)
        pk = cflib.crtp.crtpstack.CRTPPacket()  # the legacy localization-port emergency stop works too
        pk.set_header(6, 1)
        pk.data = bytes((3,))
        sims.reboot(0)
        scf.cf.send_packet(pk)
        assert _wait(lambda: sims.is_locked(0), 0.5)
    sims.reboot(0)
    with SyncCrazyflie(sims.uris[0], cf=Crazyflie()) as scf:
        scf.cf.high_level_commander.takeoff(0.5, 0.8)
        scf.cf.supervisor.send_emergency_stop_watchdog()  # armed once, never refreshed: fires after 1 s
        time.sleep(0.7)
        assert not sims.is_locked(0)
        assert _wait(lambda: sims.is_locked(0), 0.6)


def test_extpos_tightens_the_position_estimate(sims):
    with SyncCrazyflie(sims.uris[0], cf=Crazyflie()) as scf:
        truth = sims.truth(0).position

        def spread(n: int, extpos: bool) -> float:
            # A fresh LogConfig per SyncLogger: cflib gives a re-added config a new block id but keeps it
            # marked as added, so it would ask the firmware to start a block it never created (ENOENT).
            config = LogConfig("pos", 10)
            for name in ("stateEstimate.x", "stateEstimate.y"):
                config.add_variable(name, "float")
            errors = []
            with SyncLogger(scf, config) as logger:
                for _, data, _ in logger:
                    if extpos:
                        scf.cf.loc.send_extpos(truth)
                    errors.append((data["stateEstimate.x"] - truth[0], data["stateEstimate.y"] - truth[1]))
                    if len(errors) >= n:
                        return float(np.sqrt(np.mean(np.square(errors))))

        lps = spread(100, extpos=False)
        mocap = spread(100, extpos=True)
        assert 0.005 < lps < 0.1 and mocap < 0.01
        # The estimate follows the external positions, not the simulator's truth.
        offset = (truth[0] + 0.3, truth[1] - 0.2, truth[2])
        for _ in range(5):
            scf.cf.loc.send_extpos(offset)
            time.sleep(0.02)
        est = _first_log(scf, ["stateEstimate.x", "stateEstimate.y"])
        assert est["stateEstimate.x"] == pytest.approx(offset[0], abs=0.02)
        assert est["stateEstimate.y"] == pytest.approx(offset[1], abs=0.02)


@pytest.mark.parametrize("sims", [3], indirect=True)
def test_cflib_swarm_of_three_takes_off_and_lands(sims, tmp_path):
    factory = CachedCfFactory(rw_cache=str(tmp_path))
    with Swarm(sims.uris, factory=factory) as swarm:
        positions = swarm.get_estimated_positions()
        assert set(positions) == set(sims.uris)
        for i, uri in enumerate(sims.uris):
            assert np.allclose(positions[uri], sims.truth(i).position, atol=0.15)

        def takeoff(scf):
            scf.cf.high_level_commander.takeoff(0.3, 0.8)

        def land(scf):
            scf.cf.high_level_commander.land(0.0, 0.8)

        swarm.parallel_safe(takeoff)
        time.sleep(1.0)
        assert all(sims.truth(i).position[2] == pytest.approx(0.3, abs=0.03) for i in range(3))
        swarm.parallel_safe(land)
        assert _wait(lambda: all(sims.truth(i).supervisor == "landed" for i in range(3)), 5.0)
        assert all(sims.truth(i).position[2] == 0.0 for i in range(3))


@pytest.mark.slow  # cflib's estimator wait needs 10 variance samples 0.5 s apart: about 6 s
@pytest.mark.parametrize("sims", [2], indirect=True)
def test_cflib_swarm_reset_estimators_waits_for_the_variance_to_settle(sims):
    with Swarm(sims.uris, factory=CachedCfFactory()) as swarm:
        t0 = time.monotonic()
        swarm.reset_estimators()  # kalman.resetEstimation 1 then 0, then waits for kalman.varP* to settle
        assert time.monotonic() - t0 >= 4.5
        for i in range(2):
            assert sims.param(i, "kalman.resetEstimation") == 0
        est = swarm.get_estimated_positions()
        assert all(np.allclose(est[u], sims.truth(i).position, atol=0.15) for i, u in enumerate(sims.uris))


def test_swarm_gs_sim_command_serves_cflib():
    base = free_base_port(2)
    proc = subprocess.Popen([sys.executable, "-m", "groundstation.cli", "sim", "--drones", "2", "--base-port",
                             str(base), "--duration", "20"], stdout=subprocess.PIPE, text=True)
    try:
        lines = [proc.stdout.readline() for _ in range(3)]
        assert f"udp://127.0.0.1:{base + 1}" in lines[2]
        with SyncCrazyflie(f"udp://127.0.0.1:{base + 1}", cf=Crazyflie()) as scf:
            assert scf.cf.platform.get_protocol_version() == crtp.PROTOCOL_VERSION
    finally:
        proc.terminate()
        assert proc.wait(timeout=5) == 0


# ---- the pure parts ------------------------------------------------------------------------------

def test_noise_is_deterministic_under_a_seed():
    def run(seed):
        batch = QuadBatch(2, QuadParams(), np.zeros((2, 3)), seed)
        for _ in range(50):
            batch.step(0.01, np.zeros((2, 3)), np.zeros(2), np.zeros(2, dtype=bool))
        return batch.estimated_position(1, False)

    assert np.array_equal(run(3), run(3)) and not np.array_equal(run(3), run(4))


def test_flight_model_limits_speed_and_rests_on_the_ground():
    params = QuadParams()
    batch = QuadBatch(1, params, np.array([[0.0, 0.0, 1.0]]), 0)
    on = np.ones(1, dtype=bool)
    for _ in range(300):
        batch.step(0.01, np.array([[10.0, 0.0, 0.0]]), np.zeros(1), on)
    assert np.linalg.norm(batch.vel[0, :2]) == pytest.approx(params.max_speed_xy)
    for _ in range(300):
        batch.step(0.01, np.zeros((1, 3)), np.zeros(1), ~on)  # motors off: it falls and stops on the floor
    assert batch.pos[0, 2] == 0.0 and np.all(batch.vel[0] == 0.0)
    assert batch.charge_as[0] < params.battery_capacity_as


def test_firmware_watchdog_timeline_without_sockets():
    fw = Firmware(QuadParams(), now=0.0)
    pos, vel = np.array([0.0, 0.0, 0.5]), np.zeros(3)
    fw.control(0.0, pos, vel, 0.0)
    assert fw.state is SupervisorState.READY and not fw.motors_on  # the idle planner's null setpoint
    fw.stream(0.0, Mode.VELOCITY, (0.3, 0.0, 0.1, 0.0))
    assert fw.control(0.01, pos, vel, 0.0)[2:] == (True, False)
    fw.control(0.49, pos, vel, 0.0)
    assert fw.state is SupervisorState.FLYING
    v, _, on, coasting = fw.control(0.51, pos, vel, 0.0)
    assert fw.state is SupervisorState.LEVEL_OUT and on and coasting
    assert v[2] == pytest.approx(0.1)  # z keeps the setpoint's mode: a vertical velocity goes on
    fw.control(2.01, pos, vel, 0.0)
    assert fw.state is SupervisorState.LOCKED and not fw.motors_on
    assert fw.arm(True) == (False, False)


def test_firmware_emergency_stop_watchdog_and_landed_timeline():
    fw = Firmware(QuadParams(), now=0.0)
    pos, vel = np.array([0.0, 0.0, 0.0]), np.zeros(3)
    fw.emergency_stop_watchdog(0.0)
    assert fw.hl_takeoff(0.0, 0, pos, 0.0, 0.5, 1.0, None)
    fw.control(0.01, pos, vel, 0.0)
    fw.control(0.02, pos, vel, 0.0)
    assert fw.state is SupervisorState.FLYING and fw.motors_on
    assert not fw.hl_takeoff(0.03, 0, pos, 0.0, 0.5, 1.0, None)  # plan_takeoff: only from idle
    fw.emergency_stop_watchdog(0.9)
    fw.control(1.5, pos, vel, 0.0)
    assert fw.state is SupervisorState.FLYING  # fed in time
    assert fw.hl_land(1.5, 0, pos, 0.0, 0.0, 0.5, None)
    fw.emergency_stop_watchdog(1.8)
    fw.control(2.0, pos, vel, 0.0)
    fw.control(2.0 + 0.01, pos, vel, 0.0)  # the landing has ended: the planner is idle, motors off
    assert not fw.motors_on and fw.state is SupervisorState.FLYING  # "flying" until idle for 2 s
    fw.emergency_stop_watchdog(3.5)
    fw.control(4.05, pos, vel, 0.0)
    assert fw.state is SupervisorState.LANDED  # the watchdog is not judged while landed ...
    fw.control(7.1, pos, vel, 0.0)
    assert fw.state is SupervisorState.LOCKED  # ... but the reset after the landing timeout locks


def test_drones_that_touch_both_crash_and_are_counted_once():
    starts = np.array([[0.0, 0.0, 0.0], [0.6, 0.0, 0.0], [3.0, 0.0, 0.0], [3.1, 0.0, 0.0]])
    sims = SimSwarm(4, base_port=free_base_port(4), start_positions=starts)  # not started: stepped by hand
    t, dt = 0.0, sims.physics_dt
    # drones 0 and 1 swap places at 0.5 m height; 2 and 3 rest side by side, 0.1 m apart (no contact)
    for _ in range(int(3.0 / dt)):
        for i, x in ((0, 0.6), (1, 0.0)):
            sims.drones[i].firmware.stream(t, Mode.POSITION, (x, 0.0, 0.5, 0.0))
        sims._physics_step(t, dt)
        t += dt
    assert sims.drone_contacts == 1 and [e[1:] for e in sims.contact_events] == [(0, 1)]
    assert sims.is_locked(0) and sims.is_locked(1) and not sims.is_locked(2) and not sims.is_locked(3)
    assert all(sims.truth(i).position[2] == 0.0 and not sims.truth(i).motors_on for i in range(4))
    gap = abs(sims.truth(0).position[0] - sims.truth(1).position[0])
    assert gap < 0.6  # they met on the way (and fell there), they did not pass through each other


def test_a_cflib_link_sends_no_latency_pings(sims):
    """cflib pings every connection 10 times a second from a thread of its own for a latency figure the ground
    station never reads; ``CflibLink`` stops it (12 links: 12 threads and 240 packets/s less in the demo)."""
    from flight_fixtures import open_sim_links
    from groundstation.flight import close_links
    link = open_sim_links(sims.uris[:1])[0]
    try:
        pinger = link._cf.link_statistics.latency._ping_thread_instance
        assert pinger is None or not pinger.is_alive()
        assert link.telemetry() is not None and link.telemetry().battery > 3.0  # the link itself is up
    finally:
        close_links([link])
