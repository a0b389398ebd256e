"""A ``FlightSession`` flies simulated ArduCopter and PX4 vehicles over ``MavlinkLink`` (real pymavlink on both
sides) through the failsafes.

Four vehicles, two of each firmware, take off and hover under the session's setpoint stream (PX4 switches to
OFFBOARD on it). Then the radio of one of each goes silent in both directions: the session marks them lost and
keeps sending land commands that nobody acknowledges, while it lands the two healthy vehicles. Checked: the
silent ones come down by their firmware's own failsafe (ArduCopter: GCS failsafe, LAND after its pause; PX4:
offboard loss, LAND) and end disarmed; the healthy ones land and disarm; and the supervisor never waited on
the silent vehicles' acknowledgements (its flight-log rows keep their rate throughout).
"""
from __future__ import annotations

import logging
import time

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from flight_fixtures import quick_flight, wait_until  # noqa: E402
from groundstation.flight import DroneStatus, FlightSession, JsonlRecorder, close_links  # noqa: E402
from groundstation.link import open_link  # noqa: E402
from groundstation.mavlink_autopilot import Autopilot  # noqa: E402
from groundstation.roles import PURSUER_TEAM  # noqa: E402
from groundstation.safety import FenceConfig  # noqa: E402
from groundstation.sim.mavlink_vehicle import LAND_PAUSE, MavlinkVehicle, VehicleConfig  # noqa: E402
from groundstation.sim.swarm import free_base_port  # noqa: E402

DRONES = {"ap0": Autopilot.ARDUPILOT, "ap1": Autopilot.ARDUPILOT, "px0": Autopilot.PX4, "px1": Autopilot.PX4}
SILENCED = ("ap1", "px1")


@pytest.fixture(scope="module")
def flight():
    fence = FenceConfig(box=(-2.0, 2.0, -2.0, 2.0), z_min=0.2, z_max=1.5, margin=0.2)
    port = free_base_port(len(DRONES), seed=16)
    vehicles = {}
    for i, (d, autopilot) in enumerate(DRONES.items()):
        cfg = VehicleConfig(autopilot=autopilot, system_id=i + 1)
        vehicles[d] = MavlinkVehicle(f"udpout:127.0.0.1:{port + i}", cfg, start=(-1.2 + 0.8 * i, 0.0, 0.0),
                                     seed=i).start()
    links = {}
    out: dict = {"vehicles": vehicles}
    warnings = _Collect()  # the vehicles' and the links' warnings, for the assertions' messages
    logging.getLogger().addHandler(warnings)
    out["log"] = warnings.lines
    try:
        for i, d in enumerate(DRONES):
            links[d] = open_link(f"mavlink:udpin:127.0.0.1:{port + i}", connect_timeout=5.0)
            links[d].upload_fence(fence)  # the vehicle's own backstop, the way its firmware takes it
        recorder = JsonlRecorder()
        # a generous takeoff limit: four vehicles, their links and the supervisor share one test process, so on a
        # loaded machine their threads run late; what is checked is that each takes off, not how fast (failed once
        # in a CI check with the default 6 s: 3 of 4 vehicles not flying when takeoff() returned, the cause not
        # recorded then; the assertion now says it)
        session = FlightSession(links, {d: PURSUER_TEAM for d in DRONES}, fence, quick_flight(takeoff_timeout=30.0),
                                record=recorder)
        with session:
            out["preflight"] = session.preflight(timeout=10.0)  # disarmed on the ground is ready for MAVLink
            out["flying"] = session.takeoff()
            # why a drone is not flying, for the assertion's message: its events and its link's refused commands
            out["takeoff_log"] = {d: ([f"{e.kind}: {e.detail}" for e in session.events if e.drone == d],
                                      list(links[d].command_errors), session.status(d).value)
                                  for d in DRONES if d not in out["flying"]}
            # PX4 flies the stream only in OFFBOARD, which the link asks for once the stream runs
            out["offboard"] = wait_until(lambda: all(vehicles[d].flight_mode == "OFFBOARD" for d in DRONES
                                                     if DRONES[d] is Autopilot.PX4), 20.0)
            out["modes_in_flight"] = {d: v.flight_mode for d, v in vehicles.items()}
            t_cut = time.monotonic()
            for d in SILENCED:
                vehicles[d].kill_link()
            wait_until(lambda: all(session.status(d) is DroneStatus.LOST for d in SILENCED), 20.0)
            out["statuses_lost"] = session.statuses()
            for d in DRONES:
                if d not in SILENCED:
                    session.land(d, "test: end of flight")
            wait_until(lambda: all(session.status(d) is DroneStatus.LANDED for d in DRONES if d not in SILENCED),
                       60.0)
            # the silent vehicles land by themselves; the session keeps asking them to, unanswered
            # generous: on a loaded machine the threads run late; the vehicles' own timers say how long it takes
            # down = disarmed and on the ground: a vehicle disarms when its land detector fires at 2 cm and then
            # drops the last centimetres in its next physics steps (failed once under load: disarmed at 3 mm)
            out["silent_down"] = wait_until(lambda: all(not vehicles[d].armed and vehicles[d].position[2] == 0.0
                                                        for d in SILENCED), 60.0)
            out["silent_down_after"] = time.monotonic() - t_cut
            out["statuses_end"] = session.statuses()
        out["session"] = session
        out["rows"] = [r for r in recorder.rows if "state" in r]
        out["t0"] = session._t0
        out["t_cut"] = t_cut
        out["errors"] = {d: links[d].command_errors for d in DRONES}
    finally:
        logging.getLogger().removeHandler(warnings)
        close_links(links.values())
        for v in vehicles.values():
            v.stop()
    return out


class _Collect(logging.Handler):
    """Keeps every WARNING and above as one line: a module fixture's log is not in the report of a later test."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(f"{record.relativeCreated / 1e3:.3f} s {record.name}: {record.getMessage()}")


def test_disarmed_vehicles_pass_preflight(flight):
    assert flight["preflight"] == {}


def test_every_vehicle_took_off_and_px4_went_offboard(flight):
    assert sorted(flight["flying"]) == sorted(DRONES), (flight["takeoff_log"], flight["log"])
    assert flight["offboard"]
    modes = flight["modes_in_flight"]
    assert all(modes[d] == ("GUIDED" if a is Autopilot.ARDUPILOT else "OFFBOARD") for d, a in DRONES.items())


def test_silent_vehicles_are_lost_and_land_on_their_own_failsafes(flight):
    assert flight["silent_down"], {d: (v.armed, v.flight_mode, v.position.tolist())
                                   for d, v in flight["vehicles"].items()}
    for d in SILENCED:
        assert flight["statuses_lost"][d] is DroneStatus.LOST
        assert flight["statuses_end"][d] is DroneStatus.LOST  # the ground station never heard back
        v = flight["vehicles"][d]
        assert not v.armed and v.position[2] == 0.0 and v.flight_mode == "LAND"
        assert v.failsafe_landings == 1
    # ArduCopter: FS_GCS_TIMEOUT 1 s, then LAND_WITH_DELAY_MS (4 s) before the descent starts
    assert flight["silent_down_after"] > 1.0 + LAND_PAUSE - 0.3
    # the land commands the session kept sending failed with a clear error, off the supervisor's thread
    for d in SILENCED:
        assert any("unanswered" in e for e in flight["errors"][d])


def test_healthy_vehicles_land_and_disarm(flight):
    for d in DRONES:
        if d in SILENCED:
            continue
        assert flight["statuses_end"][d] is DroneStatus.LANDED
        v = flight["vehicles"][d]
        assert not v.armed and v.position[2] == 0.0
        assert np.linalg.norm(v.position[:2] - v.home[:2]) < 0.3  # landed where it hovered


def test_the_supervisor_never_waited_on_the_silent_vehicles(flight):
    """Rows are written by the supervisor at record_rate (10 Hz); a supervisor blocked on one vehicle's
    acknowledgements (4 tries x 0.5 s per land command) would leave gaps of seconds in every drone's rows."""
    rows = [r for r in flight["rows"] if r["drone"] == "ap0"]
    cut = flight["t_cut"] - flight["t0"]
    times = np.array([r["t"] for r in rows if cut - 0.5 <= r["t"] <= cut + 4.0])
    # rows all through the window (a blocked supervisor wrote none for seconds after the cut: measured 2.0 s
    # per unanswered land command with a land() that waited for its ack)
    assert times[0] < cut - 0.3 and times[-1] > cut + 3.5, (times[0], times[-1], cut)
    assert np.max(np.diff(times)) < 0.5, np.max(np.diff(times))
