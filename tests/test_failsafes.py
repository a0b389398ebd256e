"""Per-drone failsafes in flight, against simulated Crazyflies driven through unmodified cflib.

One flight of six drones (2 pursuers, 2 scouts, 1 evader and one spare; the actors run in
``runtime.agent.Agent`` threads through ``AgentPilot``) is flown once for the module; 1.2 s into the mission four things go wrong at once, each to a different
drone: its link is cut in the simulator, its battery is drained, its position source stalls (the tracker is
detached from its link, which keeps delivering), and its actor's model starts answering NaN. The tests then
check how each was detected and handled, that roles were repaired, and that the two healthy drones flew on.
"""
from __future__ import annotations

import time

import pytest

pytest.importorskip("cflib")

from flight_fixtures import on_ground, open_sim_links, quick_flight, small_spec, wait_until, write_models  # noqa: E402
from groundstation.demo import draw_obstacles, start_positions  # noqa: E402
from groundstation.flight import DroneStatus, close_links, FlightSession  # noqa: E402
from groundstation.mission import AgentPilot  # noqa: E402
from groundstation.roles import EVADER_TEAM, PURSUER_TEAM  # noqa: E402
from groundstation.safety import FenceConfig  # noqa: E402
from groundstation.sim.swarm import SimSwarm, free_base_port  # noqa: E402
from runtime.policy import OnnxPolicy, load_models  # noqa: E402
from runtime.spec import Role  # noqa: E402

FAIL_AT = 1.2
"""Seconds into the mission when the failures are injected."""


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    spec = small_spec()
    root = tmp_path_factory.mktemp("failsafe-models")
    models = write_models(root / "ok", spec, seed=1)
    nan_models = write_models(root / "nan", spec, seed=1, nan_actors=spec.team.agent_ids())
    obstacles = draw_obstacles(spec, seed=3)
    fence = FenceConfig.from_spec(spec, obstacles)
    n = 6
    ids = [f"cf{i}" for i in range(n)]
    teams = {d: EVADER_TEAM if i == n - 1 else PURSUER_TEAM for i, d in enumerate(ids)}
    out: dict = {"ids": ids, "spec": spec}
    with SimSwarm(n, base_port=free_base_port(n, seed=11), seed=2,
                  start_positions=start_positions(fence, n, seed=3)) as sims:
        links = open_sim_links(sims.uris)
        try:
            _, pols = load_models(models, spec=spec)
            session = FlightSession(dict(zip(ids, links)), teams, fence, quick_flight(),
                                    actors=[{"id": p.agent_id, "role": p.role.label} for p in pols])
            with session:
                session.preflight(spec_hash=spec.hash, models_spec_hash=spec.hash)
                first = session.assign_roles()
                session.takeoff()
                out["flying_after_takeoff"] = session.flying()
                pilot = AgentPilot(session, spec, {p.agent_id: p for p in pols}, obstacles)
                with pilot:
                    pilot.begin_mission()
                    time.sleep(FAIL_AT)
                    by_role = {role: [] for role in Role}
                    for d in first.by_actor.values():
                        by_role[first.role_of_drone(d)].append(d)
                    cut, drained = by_role[Role.PURSUER]
                    stale, faulty = by_role[Role.SCOUT]
                    faulty_actor = first.by_drone[faulty]
                    out.update(cut=cut, drained=drained, stale=stale, faulty=faulty, faulty_actor=faulty_actor,
                               first=first.by_drone)
                    # four failures, one per drone
                    sims.kill_link(ids.index(cut))
                    out["cut_at"] = time.monotonic()
                    # 3 % left: past the LiPo curve's knee, the voltage under load falls below low_battery_v
                    sims.model.charge_as[ids.index(drained)] = 0.03 * sims.model.params.battery_capacity_as
                    session.tracker.detach(stale)
                    out["stale_at"] = time.monotonic()
                    pilot.set_policy(faulty_actor, OnnxPolicy(nan_models / f"{faulty_actor}.onnx", spec=spec))
                    # the four outcomes, waited for (generously: a loaded machine is slow, never a pass): the cut
                    # drone lost, the other three landed and on the ground in the simulator
                    def handled() -> bool:
                        st = session.statuses()
                        return st[cut] is DroneStatus.LOST and all(
                            st[x] is DroneStatus.LANDED and on_ground(sims.truth(ids.index(x)))
                            for x in (drained, stale, faulty))
                    wait_until(handled, 20.0)
                    out["statuses_in_flight"] = session.statuses()
                    out["roles_in_flight"] = dict(session.assignment.by_drone)
                    out["truth_in_flight"] = {d: sims.truth(i) for i, d in enumerate(ids)}
                session.stop_mission()
            out["session"] = session
            out["final"] = session.statuses()
            wait_until(lambda: all(on_ground(sims.truth(i)) for i in range(n)), 4.0)
            out["truth_final"] = {d: sims.truth(i) for i, d in enumerate(ids)}
        finally:
            close_links(links)
    return out


def test_all_took_off(flight):
    assert sorted(flight["flying_after_takeoff"]) == flight["ids"]


def test_link_cut_is_detected_within_300_ms_and_the_drone_comes_down(flight):
    s, cut = flight["session"], flight["cut"]
    lost = s.events_of("link_lost", cut)
    assert len(lost) == 1
    assert 0.0 < lost[0].t - flight["cut_at"] < 0.3
    assert flight["statuses_in_flight"][cut] is DroneStatus.LOST
    # no link, so the ground station cannot land it: the firmware's watchdog levels out and cuts the motors
    assert on_ground(flight["truth_final"][cut])
    assert not flight["truth_final"][cut].link_alive


def test_low_battery_lands_the_drone(flight):
    s, d = flight["session"], flight["drained"]
    ev = s.events_of("low_battery", d)
    assert len(ev) == 1 and ev[0].data["battery_v"] < s.config.low_battery_v
    assert flight["statuses_in_flight"][d] is DroneStatus.LANDED
    truth = flight["truth_in_flight"][d]
    assert on_ground(truth) and truth.supervisor != "locked"  # landed by its planner, not dropped


def test_stale_position_holds_then_lands(flight):
    s, d = flight["session"], flight["stale"]
    invalid = s.events_of("position_invalid", d)
    assert len(invalid) == 1
    cfg = s.config
    assert invalid[0].t - flight["stale_at"] < cfg.position_stale_after + 0.1
    statuses = [e.data["to"] for e in s.events_of("status", d)]
    assert statuses[-3:] == ["holding", "landing", "landed"]
    landing = [e for e in s.events_of("status", d) if e.data["to"] == "landing"][0]
    assert landing.t - invalid[0].t == pytest.approx(cfg.position_hold_time, abs=0.1)
    assert on_ground(flight["truth_in_flight"][d]) and flight["truth_in_flight"][d].supervisor != "locked"


def test_nan_policy_is_an_agent_fault_and_its_actor_is_retired(flight):
    s, d, actor = flight["session"], flight["faulty"], flight["faulty_actor"]
    ev = s.events_of("agent_fault", d)
    assert len(ev) == 1 and ev[0].data["actor"] == actor and ev[0].data["actor_retired"]
    assert "non-finite network output" in ev[0].detail
    assert flight["statuses_in_flight"][d] is DroneStatus.LANDED
    assert actor not in flight["roles_in_flight"].values()  # nobody inherits the broken model
    assert on_ground(flight["truth_in_flight"][d])


def test_roles_are_repaired_and_the_rest_fly_on(flight):
    s = flight["session"]
    failed = {flight[k] for k in ("cut", "drained", "stale", "faulty")}
    healthy = [d for d in flight["ids"] if d not in failed]
    assert len(healthy) == 2
    roles = flight["roles_in_flight"]
    assert not failed & set(roles)  # failed drones fly no actor
    for d in healthy:
        assert flight["statuses_in_flight"][d] is DroneStatus.FLYING
        truth = flight["truth_in_flight"][d]
        assert truth.motors_on and truth.position[2] > 0.3
    # the spare took a vacant pursuer actor, so there is still a pursuer for the evader
    spare = next(d for d in healthy if d not in flight["first"])
    assert roles[spare].startswith("pursuer_")
    assert any(c.drone_id == spare and c.new_actor == roles[spare] for c in s.role_changes)
    assert any(c.drone_id == flight["cut"] and c.new_actor is None for c in s.role_changes)
    # and at the end the session landed everyone it could reach
    assert all(flight["final"][d] is DroneStatus.LANDED for d in flight["ids"] if d != flight["cut"])
    assert all(on_ground(t) for t in flight["truth_final"].values())
    assert s.geofence_violations() == 0


def test_a_ground_station_stall_is_not_a_link_loss():
    """Every link looks silent after the ground station itself stalled: that is judged only after a short
    grace, once the receive threads had the chance to deliver what queued up."""
    from flight_fixtures import ScriptedLink

    links = {d: ScriptedLink(f"scripted://{d}") for d in ("a", "b")}
    session = FlightSession(links, {"a": PURSUER_TEAM, "b": PURSUER_TEAM}, FenceConfig(), quick_flight())
    for d in session.drones.values():
        d.status = DroneStatus.FLYING
    now = time.monotonic()
    for link in links.values():
        link.feed(t=now - 0.35)
    session._last_tick = now - 0.35  # the supervisor did not run for 350 ms either
    session._tick(now)
    assert session.stalls == 1 and not session.events_of("link_lost")
    assert session.statuses() == {"a": DroneStatus.FLYING, "b": DroneStatus.FLYING}
    links["a"].feed(t=now + 0.01)  # a's telemetry was only queued; b stays silent
    session._tick(now + 0.02)  # still in the grace period
    assert not session.events_of("link_lost")
    session._tick(now + 0.06)
    assert [e.drone for e in session.events_of("link_lost")] == ["b"]
    assert session.status("b") is DroneStatus.LOST and ("land",) == links["b"].sent[-1][:1]
    assert session.status("a") is not DroneStatus.LOST
