"""Role assignment: actors onto drones, repaired after dropouts so that pursuers never fall below evaders."""
from __future__ import annotations

import logging

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundstation.roles import (EVADER_TEAM, Assignment, DroneInfo, assign_roles, parse_actors, reassign)
from runtime.spec import Role, SpecError

# the paper's flight: 2 pursuers, 3 scouts, 1 evader
MANIFEST = ([{"id": f"pursuer_{i}", "role": "pursuer"} for i in range(2)]
            + [{"id": f"scout_{i}", "role": "scout"} for i in range(3)]
            + [{"id": "evader_0", "role": "evader"}])


def drones(batteries: list[float], evader_at: tuple[float, float] = (0.0, 0.0)) -> list[DroneInfo]:
    team = [DroneInfo(f"cf{i}", (float(i), 0.0, 1.0), b) for i, b in enumerate(batteries)]
    return team + [DroneInfo("ev0", (*evader_at, 1.0), 1.0, team=EVADER_TEAM)]


def check_invariants(a: Assignment, ds: list[DroneInfo], low: float = 0.2) -> None:
    info = {d.id: d for d in ds}
    flown = list(a.by_actor.values())
    assert len(flown) == len(set(flown)), "a drone flies two actors"
    assert set(a.by_actor) <= {x.id for x in a.actors}
    for actor_id, drone_id in a.by_actor.items():
        d = info[drone_id]
        assert d.available and d.battery >= low, f"{drone_id} is unusable but flies {actor_id}"
        role = a._actor(actor_id).role
        assert (d.team == EVADER_TEAM) == (role is Role.EVADER)


def test_fullest_batteries_nearest_the_evader_pursue() -> None:
    ds = drones([0.5, 0.9, 0.95, 0.4, 0.6])
    a = assign_roles(MANIFEST, ds)
    check_invariants(a, ds)
    assert {a.drone_of("pursuer_0"), a.drone_of("pursuer_1")} == {"cf1", "cf2"}
    assert a.drone_of("evader_0") == "ev0"
    assert a.count(Role.SCOUT) == 3 and a.vacant == ()
    # equal batteries: the drones nearest the evader pursue
    ds = drones([0.8] * 5, evader_at=(4.0, 0.0))
    a = assign_roles(MANIFEST, ds)
    assert {a.drone_of("pursuer_0"), a.drone_of("pursuer_1")} == {"cf3", "cf4"}


def test_too_few_drones_fly_pursuers_first_and_skip_low_ones() -> None:
    ds = drones([0.9, 0.1, 0.8])  # cf1 is below the low-battery threshold
    a = assign_roles(MANIFEST, ds)
    check_invariants(a, ds)
    assert a.count(Role.PURSUER) == 2 and a.count(Role.SCOUT) == 0
    assert set(a.vacant) == {"scout_0", "scout_1", "scout_2"}


def test_a_scout_takes_over_a_lost_pursuer_and_it_is_logged(caplog: pytest.LogCaptureFixture) -> None:
    ds = drones([0.9, 0.8, 0.5, 0.4, 0.3])
    a = assign_roles(MANIFEST, ds)
    lost = a.drone_of("pursuer_0")
    ds = [DroneInfo(d.id, d.position, d.battery, d.id != lost, d.team) for d in ds]
    with caplog.at_level(logging.INFO, logger="groundstation.roles"):
        b, changes = reassign(a, ds, n_evaders=1)
    check_invariants(b, ds)
    assert b.count(Role.PURSUER) == 2 and b.count(Role.SCOUT) == 2
    promoted = b.drone_of("pursuer_0")
    assert a.role_of_drone(promoted) is Role.SCOUT
    assert promoted == "cf2"  # the fullest scout
    assert [c.reason for c in changes] == ["drone unavailable", "scout promoted to a vacant pursuer actor"]
    assert sum("role change" in r.getMessage() for r in caplog.records) == 2


def test_idle_drones_fill_before_scouts_and_low_battery_releases() -> None:
    ds = drones([0.9, 0.8, 0.5, 0.4, 0.3]) + [DroneInfo("spare", (0.0, 0.0, 0.0), 1.0)]
    a = assign_roles(MANIFEST, ds[:6])  # the spare is not there yet
    assert "spare" not in a.by_actor.values()
    low = a.drone_of("pursuer_1")
    ds = [DroneInfo(d.id, d.position, 0.1 if d.id == low else d.battery, True, d.team) for d in ds]
    b, changes = reassign(a, ds, n_evaders=1)
    check_invariants(b, ds)
    assert b.drone_of("pursuer_1") == "spare"
    assert changes[0].reason.startswith("battery 0.10 below")
    assert len(changes) == 2
    same, none = reassign(b, ds, n_evaders=1)
    assert none == [] and same.by_actor == b.by_actor


def test_a_returning_drone_fills_a_vacant_scout() -> None:
    ds = drones([0.9, 0.8, 0.5, 0.4, 0.3])
    a = assign_roles(MANIFEST, ds)
    gone = a.drone_of("scout_1")
    b, _ = reassign(a, [d for d in ds if d.id != gone], n_evaders=1)
    assert "scout_1" in b.vacant
    c, changes = reassign(b, ds, n_evaders=1)
    assert c.drone_of("scout_1") == gone and len(changes) == 1


def test_bad_manifests_and_drones_are_refused() -> None:
    with pytest.raises(SpecError, match=r"manifest.agents\[1\].id"):
        parse_actors([{"id": "a", "role": "pursuer"}, {"id": "a", "role": "scout"}])
    with pytest.raises(SpecError, match="unknown role"):
        parse_actors([{"id": "a", "role": "chaser"}])
    with pytest.raises(SpecError, match=r"manifest.agents\[0\]"):
        parse_actors([{"role": "scout"}])
    with pytest.raises(ValueError, match="unique"):
        assign_roles(MANIFEST, [DroneInfo("x"), DroneInfo("x")])


def test_too_few_pursuers_warns(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="groundstation.roles"):
        assign_roles([{"id": "p", "role": "pursuer"}, {"id": "e0", "role": "evader"},
                      {"id": "e1", "role": "evader"}],
                     [DroneInfo("a"), DroneInfo("e0", team=EVADER_TEAM), DroneInfo("e1", team=EVADER_TEAM)])
    assert any("assumption (a)" in r.getMessage() for r in caplog.records)


# -- properties ----------------------------------------------------------------------------------------


@st.composite
def scenario(draw: st.DrawFn) -> tuple[list[dict], list[DroneInfo], list[list[tuple[str, bool, float]]]]:
    n_e = draw(st.integers(1, 3))
    n_p = draw(st.integers(n_e, 5))
    n_s = draw(st.integers(0, 5))
    manifest = ([{"id": f"pursuer_{i}", "role": "pursuer"} for i in range(n_p)]
                + [{"id": f"scout_{i}", "role": "scout"} for i in range(n_s)]
                + [{"id": f"evader_{i}", "role": "evader"} for i in range(n_e)])
    n_team = draw(st.integers(n_e, n_p + n_s + 2))
    pos = st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(0, 2))
    ds = [DroneInfo(f"d{i}", draw(pos), draw(st.floats(0, 1))) for i in range(n_team)]
    ds += [DroneInfo(f"e{i}", draw(pos), 1.0, team=EVADER_TEAM) for i in range(n_e)]
    events = draw(st.lists(st.lists(st.tuples(st.sampled_from([d.id for d in ds]), st.booleans(),
                                              st.floats(0, 1)), max_size=4), max_size=8))
    return manifest, ds, events


@settings(max_examples=200, deadline=None)
@given(scenario())
def test_any_sequence_of_dropouts_keeps_the_invariants(sc: tuple) -> None:
    manifest, ds, events = sc
    a = assign_roles(manifest, ds)
    check_invariants(a, ds)
    n_e = sum(1 for m in manifest if m["role"] == "evader")
    n_p = sum(1 for m in manifest if m["role"] == "pursuer")
    state = {d.id: d for d in ds}
    for step in events:
        for drone_id, available, battery in step:
            d = state[drone_id]
            state[drone_id] = DroneInfo(d.id, d.position, battery, available, d.team)
        now = list(state.values())
        a, changes = reassign(a, now, n_evaders=n_e)
        check_invariants(a, now)
        usable_team = sum(1 for d in now if d.team != EVADER_TEAM and d.available and d.battery >= 0.2)
        assert a.count(Role.PURSUER) == min(n_p, usable_team)
        if usable_team >= n_e:
            assert a.count(Role.PURSUER) >= n_e
        for c in changes:
            assert c.old_actor != c.new_actor
