"""A positioning dropout in flight: the simulated estimator's variance grows as the Crazyflie's Kalman filter
makes it grow without measurements, and the ground station's variance failsafe holds and then lands that
drone while the other flies on."""
from __future__ import annotations

import pytest

pytest.importorskip("cflib")

from flight_fixtures import on_ground, open_sim_links, quick_flight, wait_until  # noqa: E402
from groundstation.flight import DroneStatus, FlightSession, close_links  # noqa: E402
from groundstation.safety import FenceConfig  # noqa: E402
from groundstation.sim.swarm import SimSwarm, free_base_port  # noqa: E402


def test_a_positioning_dropout_grows_the_variance_and_the_failsafe_lands_the_drone():
    ids = ["cf0", "cf1"]
    with SimSwarm(2, base_port=free_base_port(2, seed=31), seed=3) as sims:
        links = open_sim_links(sims.uris)
        try:
            session = FlightSession(dict(zip(ids, links)), {d: "pursuer" for d in ids}, FenceConfig(),
                                    quick_flight())
            with session:
                session.preflight()
                session.takeoff()
                assert session.flying() == ids
                before = links[0].telemetry().position_variance
                sims.positioning_outage(0, 10.0)  # no measurement reaches cf0 any more
                assert wait_until(lambda: session.events_of("position_invalid", "cf0"), 5.0)
                ev = session.events_of("position_invalid", "cf0")[0]
                assert ev.detail.startswith("variance")  # judged on the estimator's variance, not on silence
                assert wait_until(lambda: session.status("cf0") in (DroneStatus.LANDING, DroneStatus.LANDED), 3.0)
                assert "position stale or invalid" in session.drones["cf0"].reason
                assert session.status("cf1") is DroneStatus.FLYING  # the other flies on
                assert wait_until(lambda: on_ground(sims.truth(0)), 5.0)
                after = links[0].telemetry().position_variance
                assert max(before) < session.config.max_position_variance < max(after)
        finally:
            close_links(links)
