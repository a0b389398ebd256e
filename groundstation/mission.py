"""The per-drone runtimes flying a ground-station mission: one ``runtime.agent.Agent`` per actor.

``AgentPilot`` runs the trained actors the way the runtime runs them everywhere else: one ``Agent`` thread
per actor (staggered over the control period), each building its own observation with the one encoder from
its own state and what it hears from its teammates over a simulated radio (``runtime.comms.Radio`` on an
``InProcessBus``), and publishing a velocity. Plugged into a ``FlightSession``:

- state source (``SessionSource``): the actor's index -> the drone that flies it now (the session's role
  assignment, so role changes are followed at the next tick) -> that drone's fresh state from the session's
  position tracker; the other team's drones as its sensors would see them; the obstacles. No drone, a
  drone that is not flying, or a stale state: no state (the agent publishes the safe action).
- command sink: ``session.set_command(drone, velocity)``; the session puts it through the geofence.
- faults: a non-finite network output for ``fault_ticks`` ticks in a row is an agent fault of the actor's
  model (the session lands the drone and retires the actor, so no other drone inherits it); other faults
  in a row (exceptions in the loop) are an agent fault of the drone. Missing state is not a fault here: the
  session's own failsafes judge stale positions.

An actor without a drone (its drone left, or the fleet is smaller than the team) never broadcasts, and with
full observability an agent waits until it has heard every teammate once. The pilot therefore broadcasts
for vacant actors: the last state of the drone that flew it, or, for an actor never flown, a parked state
outside the arena (``PARK_OFFSET`` beyond a corner) where it is the farthest teammate of everyone.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from typing import Callable, Mapping

import numpy as np

from runtime.agent import Agent, AgentConfig, Perception, staggered
from runtime.comms import CommConfig, InProcessBus, Radio
from runtime.policy import OnnxPolicy
from runtime.spec import SwarmSpec

log = logging.getLogger(__name__)

StepCallback = Callable[[float, np.ndarray, np.ndarray, np.ndarray], None]
"""``on_step(t, pos [N, 2], vel [N, 2], present [N] bool)`` once per control period from the mission's start
(``AgentPilot.begin_mission``; ``t`` counts from it), actors in spec order."""

PARK_OFFSET = 1.0
"""How far beyond the arena's corner a never-flown actor is parked [m]."""
_RETIRE_FAULT = "non-finite network output"


class SessionSource:
    """``StateSource`` over a ``FlightSession``: see the module docstring."""

    def __init__(self, session, spec: SwarmSpec, obstacles: np.ndarray) -> None:
        self.session = session
        self.spec = spec
        self.agent_ids = spec.team.agent_ids()
        nt, n = spec.team.n_team, spec.n_agents
        self.other_team = np.zeros((n, n), dtype=bool)
        self.other_team[:nt, nt:] = True
        self.other_team[nt:, :nt] = True
        self.full = spec.sensing.observability == "full"
        self.sensing_range = spec.sensing.sensing_range
        obs = np.asarray(obstacles, dtype=float).reshape(-1, 3)
        k = spec.arena.n_obstacles
        if len(obs) < k:
            raise ValueError(f"the actors observe {k} obstacles, {len(obs)} were given: give every obstacle "
                             f"(the fence's keep-out circles) as (x, y, radius)")
        order = np.argsort(np.hypot(obs[:, 0], obs[:, 1]) - obs[:, 2])[:k]  # the K most central
        self.obstacles = obs[order]

    def state(self, actor: str):
        """(drone id, fresh DroneState) of the drone flying ``actor``, or (drone, None) / (None, None)."""
        s = self.session
        drone = s.assignment.by_actor.get(actor)
        if drone is None or not s.is_flying(drone):
            return drone, None
        return drone, s.tracker.fresh(drone)

    def why_not(self, index: int) -> str:
        """Why ``self(index, p)`` had no fresh state for actor ``index`` (the agent's fault message ends with it)."""
        actor = self.agent_ids[index]
        s = self.session
        drone = s.assignment.by_actor.get(actor)
        if drone is None:
            return f"no drone flies actor {actor}"
        if not s.is_flying(drone):
            return f"drone {drone} (actor {actor}) is not flying"
        age = s.tracker.age(drone)
        if math.isinf(age):
            return f"no position of drone {drone} (actor {actor}) yet"
        return (f"the position of drone {drone} (actor {actor}) is {age:.2f} s old "
                f"(stale after {s.tracker.stale_after:.2f} s)")

    def __call__(self, index: int, p: Perception) -> bool:
        _, me = self.state(self.agent_ids[index])
        if me is None:
            return False
        p.pos[:] = me.position[:2]
        p.vel[:] = me.velocity[:2]
        p.time_s = me.t
        p.episode = 0
        p.obstacle_pos[:] = self.obstacles[:, :2]
        p.obstacle_radius[:] = self.obstacles[:, 2]
        p.sensed[:] = False
        for j in np.flatnonzero(self.other_team[index]).tolist():
            _, other = self.state(self.agent_ids[j])
            if other is None:
                continue
            p.others_pos[j] = other.position[:2]
            p.others_vel[j] = other.velocity[:2]
            p.sensed[j] = self.full or math.hypot(other.position[0] - me.position[0],
                                                  other.position[1] - me.position[1]) <= self.sensing_range
        return True


class AgentPilot:
    """The actors of a models folder flying a ``FlightSession``. ``start()`` / ``stop()``; a context manager."""

    def __init__(self, session, spec: SwarmSpec, policies: Mapping[str, OnnxPolicy], obstacles: np.ndarray,
                 on_step: StepCallback | None = None, fault_ticks: int = 3, comms: CommConfig | None = None) -> None:
        self.session = session
        self.spec = spec
        self.agent_ids = spec.team.agent_ids()
        missing = [a for a in self.agent_ids if a not in policies]
        if missing:
            raise ValueError(f"no policy for actor {missing[0]!r}: the models folder must hold one actor per agent "
                             f"of the spec ({', '.join(self.agent_ids)})")
        n = spec.n_agents
        self.period = spec.timing.control_period
        self.source = SessionSource(session, spec, obstacles)
        self.bus = InProcessBus(n)
        self.radios = [Radio(spec, i, self.bus.endpoint(i), comms) for i in range(n)]
        self._ghosts = [Radio(spec, i, self.bus.endpoint(i), comms) for i in range(n)]
        phases = staggered(n, self.period)
        self.agents = [Agent(i, spec, policies[a], self.source, self._sink, self.radios[i],
                             AgentConfig(phase_s=phases[i], lead_s=min(0.002, self.period / 4)),
                             on_fault=self._on_fault)
                       for i, a in enumerate(self.agent_ids)]
        self._warm_up(policies)
        self.on_step = on_step
        self.fault_ticks = fault_ticks
        self._fault_run = [0] * n
        self._faulted_tick = [False] * n
        self._retire_run = [0] * n
        hw = spec.arena.half_width + PARK_OFFSET
        self._park = np.array([[-hw - 0.3 * i, -hw] for i in range(n)])
        self._last = [None] * n  # last (t, pos, vel) of each actor's drone
        self._pos = np.zeros((n, 2))
        self._vel = np.zeros((n, 2))
        self._stop = threading.Event()
        self._start_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._t0 = 0.0
        self._mission_t0: float | None = None
        self.ticks = 0
        """Control periods of the pilot's own loop (metrics and broadcasts for vacant actors)."""

    # ---- lifecycle ---------------------------------------------------------------------------------

    def _warm_up(self, policies: Mapping[str, OnnxPolicy]) -> None:
        """Every actor once on its agent's (zero) observation: onnxruntime's first call allocates and plans, and
        a compiled engine builds its buffers. Construct the pilot on the ground, before the takeoff: the
        agents' constructors compile numba's kernels too, and either may hold the interpreter for seconds on a
        cold, busy machine. Faults found here are the runtime's to report in flight, not here."""
        for agent in self.agents:
            try:
                agent.policy.act(agent.obs, out=agent.action)
            except Exception as exc:  # the agent's own fault handling reports it at its first tick
                log.warning("%s: warm-up run failed: %s", agent.agent_id, exc)
            agent.action[:] = 0.0

    def start(self) -> "AgentPilot":
        self._t0 = time.monotonic() + 0.05
        self._broadcast_vacant(time.monotonic())
        self._start_assigned(self.session.assignment)
        self.session.role_listeners.append(self._start_assigned)
        self._thread = threading.Thread(target=self._run, name="AgentPilot", daemon=True)
        self._thread.start()
        return self

    def _start_assigned(self, assignment) -> None:
        """Start the agent of every actor that has a drone (an actor never flown needs no loop)."""
        with self._start_lock:
            if self._stop.is_set():
                return
            for agent, actor in zip(self.agents, self.agent_ids):
                if actor in assignment.by_actor and not agent.running:
                    agent.start(self._t0)

    def begin_mission(self, timeout: float = 60.0, poll: float = 0.01) -> float:
        """Start the session's mission once every flying drone's runtime has produced its first command from its
        actor (numba compiled, onnxruntime warmed, first observation built, teammates heard); until then the
        drones hover and nothing counts. A slow start delays the mission; a runtime that produced nothing in
        ``timeout`` seconds is an agent fault of its drone (it lands, the rest fly). Returns the mission's start
        (``time.monotonic()``); ``on_step`` times count from it."""
        deadline = time.monotonic() + timeout
        waiting = self.not_ready()
        while waiting and time.monotonic() < deadline and not self._stop.is_set():
            time.sleep(poll)
            waiting = self.not_ready()
        for actor, drone in waiting.items():
            self.session.report_agent_fault(
                drone, f"actor {actor}: its runtime produced no command in {timeout:.0f} s of start-up "
                       f"(a model that cannot run here, or a machine too busy: see the log)")
        self.session.start_mission()
        self._mission_t0 = time.monotonic()
        return self._mission_t0

    def not_ready(self) -> dict[str, str]:
        """{actor: drone} of the flying drones whose runtime has not yet produced a command from its actor."""
        out = {}
        for agent, actor in zip(self.agents, self.agent_ids):
            drone = self.session.assignment.by_actor.get(actor)
            if drone is not None and self.session.is_flying(drone) and agent.stats.actions == 0:
                out[actor] = drone
        return out

    def stop(self) -> None:
        with self._start_lock:
            self._stop.set()
        if self._start_assigned in self.session.role_listeners:
            self.session.role_listeners.remove(self._start_assigned)
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for a in self.agents:
            if a.running:
                a.stop()

    def __enter__(self) -> "AgentPilot":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def set_policy(self, actor: str, policy: OnnxPolicy) -> None:
        """Swap the model an actor runs (takes effect at its next tick)."""
        agent = self.agents[self.agent_ids.index(actor)]
        if policy.role is not agent.role:
            raise ValueError(f"{actor} is a {agent.role.label}, the policy is a {policy.role.label} actor")
        agent.policy = policy

    # ---- stats -------------------------------------------------------------------------------------

    def stats(self) -> dict:
        """Summed agent counters and the tick-to-command timings of every agent [ms]."""
        tta = np.concatenate([a.stats.timings()[0] for a in self.agents]) * 1e3
        keys = ("ticks", "actions", "faults", "no_state", "waiting", "deadline_misses", "skipped")
        out = {k: int(sum(getattr(a.stats, k) for a in self.agents)) for k in keys}
        out["tick_to_command_p99_ms"] = float(np.percentile(tta, 99)) if tta.size else None
        out["tick_to_command_p50_ms"] = float(np.percentile(tta, 50)) if tta.size else None
        return out

    # ---- the agents' sink and faults (agent threads) -----------------------------------------------

    def _sink(self, index: int, velocity: np.ndarray) -> None:
        faulted = self._faulted_tick[index]
        self._faulted_tick[index] = False
        if not faulted:
            self._fault_run[index] = 0
            self._retire_run[index] = 0
        drone = self.session.assignment.by_actor.get(self.agent_ids[index])
        if drone is None:
            return
        if self._retire_run[index] >= self.fault_ticks or self._fault_run[index] >= self.fault_ticks:
            retire = self._retire_run[index] >= self.fault_ticks
            what = self.agents[index].stats.last_fault
            self.session.report_agent_fault(
                drone, f"actor {self.agent_ids[index]}: {what} for {self._fault_run[index]} control periods",
                retire_actor=retire)
            self._fault_run[index] = self._retire_run[index] = 0
            return
        self.session.set_command(drone, velocity)

    def _on_fault(self, index: int, message: str) -> None:
        if message.startswith("no fresh state"):
            return  # no drone, not flying, or a stale position: the session's failsafes decide
        self._faulted_tick[index] = True
        self._fault_run[index] += 1
        if _RETIRE_FAULT in message:
            self._retire_run[index] += 1

    # ---- the pilot's loop: vacant actors and metrics -----------------------------------------------

    def _run(self) -> None:
        next_t = self._t0
        while not self._stop.wait(max(0.0, next_t - time.monotonic())):
            now = time.monotonic()
            try:
                self._broadcast_vacant(now)
                if self.on_step is not None and self._mission_t0 is not None:
                    self.on_step(now - self._mission_t0, self._pos.copy(), self._vel.copy(), self._present.copy())
            except Exception:  # metrics or a broadcast must not take the mission down
                log.exception("agent pilot step failed")
            self.ticks += 1
            next_t += self.period
            if next_t < time.monotonic():
                next_t = time.monotonic()

    def _broadcast_vacant(self, now: float) -> None:
        n = len(self.agent_ids)
        present = np.zeros(n, dtype=bool)
        for j, actor in enumerate(self.agent_ids):
            drone, state = self.source.state(actor)
            if state is not None:
                self._last[j] = (state.t, np.array(state.position[:2]), np.array(state.velocity[:2]))
                present[j] = True
            elif drone is not None and self.session.tracker.get(drone) is not None:
                s = self.session.tracker.get(drone)
                self._last[j] = (s.t, np.array(s.position[:2]), np.zeros(2))
            last = self._last[j]
            if last is None:
                self._pos[j], self._vel[j] = self._park[j], 0.0
            else:
                self._pos[j], self._vel[j] = last[1], last[2]
            if not present[j]:
                t_state = last[0] if last is not None else 0.0
                self._ghosts[j].broadcast(now, t_state, self._pos[j], self._vel[j], None)
        self._present = present
