"""The MAVLink link's command worker (pure threading, no vehicle) and the frame helpers it relies on."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from groundstation.mavlink_autopilot import GlobalOrigin, global_to_local, local_to_global
from groundstation.mavlink_worker import CommandWorker


@pytest.fixture
def worker():
    w = CommandWorker("test-worker")
    yield w
    w.close()


def test_jobs_run_in_order_off_the_callers_thread(worker):
    seen = []
    futs = [worker.submit(f"job{i}", lambda i=i: seen.append((i, threading.current_thread().name)) or i)
            for i in range(5)]
    assert [f.result(timeout=5.0) for f in futs] == list(range(5))
    assert [i for i, _ in seen] == list(range(5)) and {n for _, n in seen} == {"test-worker"}


def test_a_job_in_flight_is_shared_not_queued_twice(worker):
    release = threading.Event()
    runs = []
    first = worker.submit("land", lambda: runs.append(1) or release.wait(5.0))
    again = worker.submit("land", lambda: runs.append(2))
    assert again is first
    release.set()
    assert first.result(timeout=5.0) is True and runs == [1]
    later = worker.submit("land", lambda: runs.append(3))  # once done, a new one runs
    later.result(timeout=5.0)
    assert later is not first and runs == [1, 3]


def test_preempt_cancels_queued_jobs_and_stops_the_running_one_at_its_next_wait(worker):
    started = threading.Event()

    def hanging_takeoff():
        started.set()
        while not worker.should_stop():
            threading.Event().wait(0.01)  # a wait for an ack that never comes
        raise RuntimeError("abandoned")

    takeoff = worker.submit("takeoff", hanging_takeoff)
    assert started.wait(5.0)
    queued = worker.submit("offboard", lambda: "never")
    worker.preempt(("takeoff", "offboard"))
    land = worker.submit("land", lambda: "landing")
    assert land.result(timeout=5.0) == "landing"
    with pytest.raises(RuntimeError, match="abandoned"):
        takeoff.result(timeout=1.0)
    assert queued.cancelled()
    assert worker.errors == ["takeoff: abandoned"]  # a cancelled job is not an error


def test_local_global_round_trip_is_exact_to_a_centimetre():
    rng = np.random.default_rng(1)
    for lat, lon in ((-35.363261, 149.165230), (47.397742, 8.545594), (0.0, 0.0), (64.1, -21.9)):
        origin = GlobalOrigin(lat, lon, 500.0)
        for x, y in rng.uniform(-50.0, 50.0, size=(20, 2)):
            lat_e7, lon_e7 = local_to_global(origin, x, y)
            assert np.allclose(global_to_local(origin, lat_e7, lon_e7), (x, y), atol=0.01)
        north = local_to_global(origin, 0.0, 111.31884502145034)  # LOCATION_SCALING_FACTOR: 1e-3 degree
        assert north[0] - round(lat * 1e7) == pytest.approx(10_000, abs=1)
