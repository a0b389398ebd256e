"""The ``Link`` contract, run over every link kind against its simulated peer (real protocols, no mocks):
``CflibLink`` (unmodified cflib, CRTP over UDP) -> simulated Crazyflie, ``MavlinkLink`` (pymavlink) ->
simulated MAVLink vehicle. What the ground station relies on: opening by URI, timestamped telemetry,
takeoff, velocity and position setpoints that move the drone, land, emergency stop, close, and a silent
peer detected from telemetry silence within 300 ms."""
from __future__ import annotations

import functools
import math
import time

import numpy as np
import pytest

from flight_fixtures import stream as _stream, wait_until
from groundstation.link import FlightState, Link, LinkError, LinkStats, Telemetry, open_link
from groundstation.sim.swarm import SimSwarm, free_base_port

PERIOD_MS = 20
LOSS_TIMEOUT = 0.25
DETECT_WITHIN = 0.3
ON_GROUND = (FlightState.LANDED, FlightState.DISARMED)


class CflibPeer:
    def __init__(self) -> None:
        pytest.importorskip("cflib")
        self.sims = SimSwarm(1, base_port=free_base_port(1), seed=5).start()
        self.uri = self.sims.uris[0]

    def truth(self) -> np.ndarray:
        return np.array(self.sims.truth(0).position)

    def kill_link(self) -> None:
        self.sims.kill_link(0)

    def stop(self) -> None:
        self.sims.stop()


class MavlinkPeer:
    def __init__(self) -> None:
        pytest.importorskip("pymavlink")
        from groundstation.sim.mavlink_vehicle import MavlinkVehicle
        port = free_base_port(1)
        self.vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", start=(0.0, 0.0, 0.0), seed=5).start()
        self.uri = f"mavlink:udpin:127.0.0.1:{port}"

    def truth(self) -> np.ndarray:
        return self.vehicle.position

    def kill_link(self) -> None:
        self.vehicle.kill_link()

    def stop(self) -> None:
        self.vehicle.stop()


@pytest.fixture(params=["cflib", "mavlink"])
def peer_link(request):
    peer = {"cflib": CflibPeer, "mavlink": MavlinkPeer}[request.param]()
    try:
        link = open_link(peer.uri, period_ms=PERIOD_MS, link_loss_timeout=LOSS_TIMEOUT, connect_timeout=5.0)
        try:
            yield peer, link
        finally:
            link.close()
    finally:
        peer.stop()


_wait = functools.partial(wait_until, period=0.005)


def _state(link: Link) -> FlightState:
    return link.telemetry().flight_state


def test_opens_by_uri_and_reports_timestamped_telemetry(peer_link):
    peer, link = peer_link
    assert isinstance(link, Link) and link.uri == peer.uri
    first = link.telemetry()
    assert isinstance(first, Telemetry)
    samples: list[Telemetry] = []
    link.add_telemetry_callback(samples.append)
    time.sleep(0.3)
    link.remove_telemetry_callback(samples.append)
    assert len(samples) >= 0.3 * 1000 / PERIOD_MS * 0.6
    last = samples[-1]
    now = time.monotonic()
    assert all(b.t >= a.t for a, b in zip(samples, samples[1:])) and 0.0 <= now - last.t < 0.1
    assert all(b.vehicle_time_ms > a.vehicle_time_ms for a, b in zip(samples, samples[1:]))
    assert len(last.position) == len(last.velocity) == 3
    assert all(math.isfinite(v) for v in last.position + last.velocity)
    assert np.allclose(last.position, peer.truth(), atol=0.15) and np.linalg.norm(last.velocity) < 0.15
    assert 3.5 < last.battery <= 4.2
    assert 0.5 < last.link_quality <= 1.0
    assert last.flight_state in ON_GROUND
    assert link.telemetry_age() < 0.1 and not link.link_lost
    stats = link.stats()
    assert isinstance(stats, LinkStats) and stats.telemetry_received >= len(samples)
    assert stats.packets_received >= stats.telemetry_received and stats.packets_sent > 0 and not stats.link_lost


def test_takeoff_velocity_and_position_setpoints_move_it_then_it_lands(peer_link):
    peer, link = peer_link
    x0, y0, _ = peer.truth()
    link.takeoff(0.5, 1.0)
    assert _wait(lambda: _state(link) is FlightState.FLYING, 0.5)
    assert _wait(lambda: link.telemetry().planner_active, 0.5)  # the onboard planner took the takeoff
    assert _wait(lambda: abs(peer.truth()[2] - 0.5) < 0.02, 2.0)
    time.sleep(0.2)  # the climb has settled
    start = peer.truth()
    _stream(lambda: link.send_velocity(0.3, 0.0, 0.0), 0.5)
    moved = peer.truth() - start
    assert moved[0] > 0.07 and abs(moved[1]) < 0.04 and abs(moved[2]) < 0.04
    assert link.telemetry().velocity[0] == pytest.approx(0.3, abs=0.1)
    target = (x0, y0 + 0.2, 0.55)
    _stream(lambda: link.send_position(*target), 1.1)
    assert np.allclose(peer.truth(), target, atol=0.06)
    assert np.allclose(link.telemetry().position, target, atol=0.15)  # the estimate, with positioning noise
    link.land(0.8)
    assert _wait(lambda: link.telemetry().planner_active, 0.5)
    assert _wait(lambda: _state(link) in ON_GROUND, 5.0)  # a Crazyflie reports landed 2 s after touchdown
    assert _wait(lambda: peer.truth()[2] == 0.0, 0.5)
    assert not link.link_lost


def test_emergency_stop_cuts_the_motors_and_locks(peer_link):
    peer, link = peer_link
    link.takeoff(0.4, 0.8)
    assert _wait(lambda: peer.truth()[2] > 0.3, 1.5)
    link.emergency_stop()
    assert _wait(lambda: _state(link) is FlightState.LOCKED, 3.0)  # generous: the next telemetry sample says it
    assert _wait(lambda: peer.truth()[2] == 0.0, 1.0)  # it falls
    time.sleep(0.1)
    assert _state(link) is FlightState.LOCKED and not link.link_lost


def test_a_silent_peer_is_detected_from_telemetry_silence_within_300_ms(peer_link):
    peer, link = peer_link
    assert link.wait_telemetry(1.0) and not link.link_lost
    t_kill = time.monotonic()
    peer.kill_link()
    assert _wait(lambda: link.link_lost, 1.0, period=0.002)
    detected = time.monotonic() - t_kill
    # Not early (the last sample may have come up to a period, or a late one more, before the cut), not late.
    assert 0.5 * LOSS_TIMEOUT <= detected <= DETECT_WITHIN, detected
    assert link.telemetry_age() > LOSS_TIMEOUT and link.stats().link_lost
    assert link.telemetry_age(now=link.telemetry().t + 0.1) == pytest.approx(0.1)


def test_close_is_idempotent_quick_and_a_closed_link_refuses_commands(peer_link):
    _, link = peer_link
    t0 = time.monotonic()
    link.close()
    assert time.monotonic() - t0 < 0.5
    link.close()
    for call in (lambda: link.send_velocity(0.0, 0.0, 0.0), lambda: link.send_position(0.0, 0.0, 0.5),
                 lambda: link.takeoff(0.5, 1.0), lambda: link.land(1.0), link.emergency_stop):
        with pytest.raises(LinkError, match="closed"):
            call()


def test_cflib_links_opened_in_parallel_create_a_missing_toc_cache_folder(tmp_path, monkeypatch):
    """The first ``make demo`` on a machine opened its links in parallel with a TOC cache folder that did not exist
    yet, and cflib's own "exists? else makedirs" raced: ``[Errno 17] File exists``. Here cflib's check is made
    slow (50 ms) so that without the folder created beforehand every link would race; all must open."""
    pytest.importorskip("cflib")
    import concurrent.futures
    import os

    from cflib.crazyflie import toccache

    cache = tmp_path / "fresh" / "toc"
    real_exists = os.path.exists

    def slow_exists(path):
        if str(path) == str(cache):
            time.sleep(0.05)
        return real_exists(path)

    monkeypatch.setattr(toccache.os.path, "exists", slow_exists)
    n = 3
    sims = SimSwarm(n, base_port=free_base_port(n, seed=31), seed=31).start()
    links = []
    try:
        with concurrent.futures.ThreadPoolExecutor(n) as ex:
            futures = [ex.submit(open_link, u, period_ms=PERIOD_MS, rw_cache=str(cache)) for u in sims.uris]
            for f in futures:
                links.append(f.result(timeout=60))
        assert cache.is_dir() and len(links) == n
        assert all(math.isfinite(link.telemetry().position[0]) for link in links)  # telemetry arrived
    finally:
        for link in links:
            link.close()
        sims.stop()
