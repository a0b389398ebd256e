"""The per-drone runtimes as the ground station runs them: ONNX actors turning observations into commands.

``PolicyPilot`` is the adapter between a ``FlightSession`` and the trained actors: every control period
(``spec.timing.control_period``) it reads each drone's state from the session's position tracker (the state
source), builds every flown actor's observation with the one encoder (``runtime.observation``), runs the
actor (``runtime.policy.OnnxPolicy``), scales the action by the role's speed exactly as the world does, and
hands the velocity to ``session.set_command`` (the command sink). It follows role changes: an actor's
observation is always built at the actor's index from the drone that currently flies it.

A non-finite network output (``OnnxPolicy`` then returns the safe zero action and counts a fault) for
``fault_ticks`` periods in a row is an agent fault of that actor's model: the session lands the drone and
retires the actor, so that no other drone inherits the broken model. An exception from an actor is treated
the same way.

Actors whose drone has left are invisible to the others (they take no observation slot); their last known
position is kept for the metrics.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Callable, Mapping

import numpy as np

from runtime.observation import encode_observations, new_knowledge, update_knowledge
from runtime.policy import OnnxPolicy
from runtime.spec import SwarmSpec
from runtime.world import pairwise_distances

log = logging.getLogger(__name__)

StepCallback = Callable[[float, np.ndarray, np.ndarray, np.ndarray], None]
"""``on_step(t, pos [N, 2], vel [N, 2], present [N] bool)`` once per control period, actors in spec order."""


def action_to_velocity(action: np.ndarray, max_speed: float) -> np.ndarray:
    """A normalised action [-1, 1]^2 as a velocity [m/s], clipped and norm-limited like ``runtime.world``."""
    a = np.clip(np.asarray(action, dtype=float), -1.0, 1.0) * max_speed
    n = float(np.hypot(a[0], a[1]))
    return a * (max_speed / n) if n > max_speed else a


class PolicyPilot:
    """Runs every flown actor once per control period. ``start()`` / ``stop()``; a context manager."""

    def __init__(self, session, spec: SwarmSpec, policies: Mapping[str, OnnxPolicy],
                 obstacles: np.ndarray, on_step: StepCallback | None = None, fault_ticks: int = 3) -> None:
        self.session = session
        self.spec = spec
        self.agent_ids = spec.team.agent_ids()
        missing = [a for a in self.agent_ids if a not in policies]
        if missing:
            raise ValueError(f"no policy for actor {missing[0]!r}: the models folder must hold one actor per agent "
                             f"of the spec ({', '.join(self.agent_ids)})")
        self.policies = dict(policies)
        self.roles = spec.roles
        self.max_speed = np.array(spec.per_agent("max_speed"))
        obs = np.asarray(obstacles, dtype=float).reshape(-1, 3)
        self.obstacle_pos = obs[None, :, :2].copy()
        self.obstacle_radius = obs[None, :, 2].copy()
        self.on_step = on_step
        self.fault_ticks = fault_ticks
        self.period = spec.timing.control_period
        n = spec.n_agents
        self._pos = np.zeros((1, n, 2))
        self._vel = np.zeros((1, n, 2))
        self._seen = np.zeros(n, dtype=bool)
        self._knowledge = new_knowledge(spec, 1)
        self._fault_run = dict.fromkeys(self.agent_ids, 0)
        self._faults_seen = {a: p.faults for a, p in self.policies.items()}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = 0.0
        self.ticks = 0
        self.overruns = 0
        self.step_times: list[float] = []
        """Seconds each control period's work took (observation, every actor, commands)."""

    def start(self) -> "PolicyPilot":
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="PolicyPilot", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def __enter__(self) -> "PolicyPilot":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            start = time.monotonic()
            try:
                self.step(start - self._t0)
            except Exception:  # keep the other drones' commands coming; a silent drone trips its timeout
                log.exception("policy pilot step failed")
            done = time.monotonic()
            self.step_times.append(done - start)
            self.ticks += 1
            next_t += self.period
            if next_t < done:
                self.overruns += 1
                next_t = done
            self._stop.wait(next_t - done)

    def step(self, t: float) -> None:
        """One control period at mission time ``t`` [s]."""
        s = self.session
        spec = self.spec
        by_actor = s.assignment.by_actor
        n = spec.n_agents
        present = np.zeros(n, dtype=bool)
        flying = set(s.flying())
        for j, actor in enumerate(self.agent_ids):
            drone = by_actor.get(actor)
            state = s.tracker.get(drone) if drone is not None else None
            if state is None:
                self._vel[0, j] = 0.0
                continue
            self._pos[0, j] = state.position[:2]
            self._vel[0, j] = state.velocity[:2]
            self._seen[j] = True
            present[j] = drone in flying
        dist = pairwise_distances(self._pos)
        gone = ~present
        dist[:, gone, :] = np.inf
        dist[:, :, gone] = np.inf
        update_knowledge(spec, self._knowledge, self._pos, self._vel, t, dist)
        active = np.nonzero(present)[0]
        if active.size:
            obs = encode_observations(spec, self._pos, self._vel, self.obstacle_pos, self.obstacle_radius,
                                      self._knowledge, t, observers=active, dist=dist)
            now = time.monotonic()
            for k, j in enumerate(active):
                self._act(j, obs[0, k], by_actor[self.agent_ids[j]], now)
        if self.on_step is not None:
            self.on_step(t, self._pos[0].copy(), self._vel[0].copy(), present & self._seen)

    def _act(self, j: int, obs_row: np.ndarray, drone: str, now: float) -> None:
        actor = self.agent_ids[j]
        pol = self.policies[actor]
        try:
            action = pol.act(obs_row[:pol.obs_dim])
        except Exception as exc:  # a broken model is the actor's fault, whichever drone flies it
            self.session.report_agent_fault(drone, f"actor {actor} raised {type(exc).__name__}: {exc}",
                                            retire_actor=True)
            return
        if pol.faults != self._faults_seen[actor]:
            self._faults_seen[actor] = pol.faults
            self._fault_run[actor] += 1
            if self._fault_run[actor] >= self.fault_ticks:
                self.session.report_agent_fault(
                    drone, f"actor {actor}: {pol.last_fault} for {self._fault_run[actor]} control periods",
                    retire_actor=True)
                return
        else:
            self._fault_run[actor] = 0
        self.session.set_command(drone, action_to_velocity(action, float(self.max_speed[j])), now)
