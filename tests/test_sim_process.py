"""``SimProcess``: the simulated Crazyflies in a child process, with the ``SimSwarm`` interface over a pipe."""
from __future__ import annotations

import os
import signal

import pytest

from flight_fixtures import wait_until
from groundstation.sim.remote import SimProcess
from groundstation.sim.swarm import SimError, free_base_port


def test_child_serves_truth_and_failure_injection_and_stop_ends_it():
    sims = SimProcess(3, base_port=free_base_port(3, seed=31), seed=1).start()
    try:
        pid = sims.pid
        assert pid != os.getpid() and len(sims.uris) == 3 and sims.n == 3
        truths = sims.truths()
        assert len(truths) == 3 and all(not t.motors_on and t.link_alive for t in truths)
        assert sims.truth(1).position == truths[1].position  # on the ground: nothing moves
        sims.kill_link(2)
        assert not sims.truth(2).link_alive
        sims.restore_link(2)
        assert sims.truth(2).link_alive
        sims.set_charge(0, 1.0)
        assert sims.truth(0).battery_v < truths[0].battery_v
        assert sims.drone_contacts == 0 and sims.contact_events == [] and sims.latency_samples() == []
        with pytest.raises(SimError, match="IndexError"):
            sims.truth(7)  # the child's error comes back as one line; the child serves on
        assert sims.is_locked(0) is False
    finally:
        sims.stop()
    assert sims.pid is None
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_a_dead_child_is_a_clear_error_and_stop_still_works():
    sims = SimProcess(1, base_port=free_base_port(1, seed=32)).start()
    try:
        os.kill(sims.pid, signal.SIGKILL)
        assert wait_until(lambda: not sims._proc.is_alive(), 30.0)
        with pytest.raises(SimError, match="simulator process is gone"):
            sims.truths()
    finally:
        sims.stop()


def test_a_taken_port_fails_at_start_with_the_fix():
    base = free_base_port(1, seed=33)
    with SimProcess(1, base_port=base):
        with pytest.raises(SimError, match="--base-port"):
            SimProcess(1, base_port=base).start()
