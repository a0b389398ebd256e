"""``groundstation.mission.SessionSource``: the state an actor's agent reads in flight, and why it had none."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from groundstation.mission import SessionSource
from groundstation.positioning import PositionTracker
from groundstation.roles import Actor, Assignment
from runtime.agent import Perception
from runtime.spec import Role, SwarmSpec


def _sample(x: float, t: float) -> SimpleNamespace:
    return SimpleNamespace(position=(x, 0.5, 0.4), velocity=(0.1, 0.0, 0.0), battery=4.0, link_quality=100.0,
                           flight_state="flying", t=t)


def test_the_source_says_why_an_actor_has_no_fresh_state():
    spec = SwarmSpec.from_dict({"team": {"n_pursuers": 2, "n_scouts": 0, "n_evaders": 1}})
    ids = spec.team.agent_ids()
    now = [10.0]
    tracker = PositionTracker(stale_after=0.2, clock=lambda: now[0])
    flying = {"cf0", "cf1"}
    actors = tuple(Actor(a, r) for a, r in zip(ids, (Role.PURSUER, Role.PURSUER, Role.EVADER)))
    session = SimpleNamespace(assignment=Assignment(actors, {ids[0]: "cf0", ids[1]: "cf1", ids[2]: "cf2"}),
                              is_flying=lambda d: d in flying, tracker=tracker)
    obstacles = np.array([[0.0, 0.0, 0.3], [1.5, 1.5, 0.2], [-1.5, 1.0, 0.25]])
    src = SessionSource(session, spec, obstacles)
    p = Perception.new(spec)

    assert not src(0, p)
    assert src.why_not(0) == f"no position of drone cf0 (actor {ids[0]}) yet"
    tracker.update("cf0", _sample(0.3, t=10.0))
    assert src(0, p) and p.pos.tolist() == [0.3, 0.5] and p.time_s == 10.0
    now[0] = 10.5
    assert not src(0, p)
    assert src.why_not(0) == f"the position of drone cf0 (actor {ids[0]}) is 0.50 s old (stale after 0.20 s)"
    assert not src(2, p)
    assert src.why_not(2) == f"drone cf2 (actor {ids[2]}) is not flying"
    session.assignment = Assignment(actors, {ids[0]: "cf0"})
    assert not src(1, p)
    assert src.why_not(1) == f"no drone flies actor {ids[1]}"
