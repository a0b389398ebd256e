"""The per-drone loop: state in, neighbours' messages in, observation, actor, velocity command out.

One ``Agent`` per drone, each on its own thread (``Agent.start``) or driven tick by tick by its owner
(``Agent.tick``). Where the state comes from and where the command goes are two small callables, so the same
loop runs against the simulated world (``runtime.swarm``) and against real drones through the ground
station:

``StateSource``  ``source(index, perception) -> bool``
    Write drone ``index``'s current state into the preallocated ``Perception`` (own position and velocity
    with their timestamp on the swarm clock, the obstacle map, the agents its own sensors see this instant)
    and return True; return False when there is no fresh state (the drone then gets the safe action). A source
    may also have ``why_not(index) -> str``, which says why it had none (no drone, not flying, a stale position):
    the fault's message and its log line then end with it.
``CommandSink``  ``sink(index, velocity)``
    Send the velocity setpoint ``[vx, vy]`` [m/s, world frame] to drone ``index``. The vector is already
    limited to the role's ``max_speed``; zero is the safe action (hold position). The array is reused by
    the next tick: copy it if it must outlive the call. A ground station passes it through its geofence.
``FaultHandler`` ``on_fault(index, message)`` (optional)
    Told about every fault (an exception in the loop, a non-finite observation or action, no fresh state).

Sensing model: a pursuer-team drone senses evaders itself (``Perception.sensed``; within the spec's
sensing range, or all of them with full observability) and hears its teammates' states and sightings over
the radio (``runtime.comms``); an evader senses the pursuer team and hears the other evaders. The
observation is the training encoder's, ``runtime.observation.encode_observations`` with ``B = 1`` and
``observers = [index]`` on the state this drone believes, computed by its bit-identical one-observer twin
``runtime.observation.OneObserverEncoder`` (numba, a few us instead of ~0.4 ms; compiled or loaded from
numba's on-disk cache when the agent is constructed, never inside a tick). ``AgentConfig(fast_encoder=False)``
calls ``encode_observations`` itself.

Timing: ticks at ``rate_hz``, offset by ``phase_s`` (a swarm staggers its agents across the period so
that they do not contend for the CPU at the same instant). ``lead_s`` before each tick the agent reads its
state, drains its radio, builds the observation and runs the actor once as a warm-up (a model idle for a
control period costs several times more: its weights and onnxruntime's code have left the caches); at the
tick it runs the actor on that observation and publishes the command, then broadcasts its own state (once
per ``broadcast_period_s``, by default the spec's control period, whatever the control rate).
``tick_to_action`` is measured from the scheduled tick to the published command, ``state_to_action`` from
the state read to the published command (it includes the observation build).

A fault never stops the loop or other agents: the drone gets the safe action, the fault is counted in
``AgentStats`` and reported to ``on_fault``; the next tick tries again. The steady-state loop writes into buffers preallocated
once (perception, belief arrays, sightings, observation, action, command, wire buffer, timing rings); what
Python cannot avoid - the tuples of decoded messages, numpy's temporaries inside ``encode_observations`` when
``fast_encoder`` is off - is freed within the tick, so memory does not grow (checked by a test with tracemalloc).
"""
from __future__ import annotations

import ctypes
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numba import njit

from runtime.comms import Neighbours, Radio
from runtime.observation import SIGHTING, OneObserverEncoder, encode_observations
from runtime.spec import Role, SpecError, SwarmSpec
from runtime.world import action_to_velocity

log = logging.getLogger(__name__)

Clock = Callable[[], float]


@dataclass
class Perception:
    """What one drone perceives at one instant; preallocated once and overwritten by its ``StateSource``."""

    pos: np.ndarray
    """[2] own position [m, world frame]."""
    vel: np.ndarray
    """[2] own velocity [m/s]."""
    obstacle_pos: np.ndarray
    """[K, 2] obstacle centres [m] (K = spec.arena.n_obstacles)."""
    obstacle_radius: np.ndarray
    """[K] obstacle radii [m]."""
    sensed: np.ndarray
    """[N] bool: agents this drone's own sensors see now (a pursuer-team drone: evaders; an evader: the
    pursuer team). Their states go in ``others_pos`` / ``others_vel``; other rows are ignored."""
    others_pos: np.ndarray
    """[N, 2] positions of the sensed agents [m]."""
    others_vel: np.ndarray
    """[N, 2] velocities of the sensed agents [m/s]."""
    time_s: float = 0.0
    """Timestamp of this state on the swarm clock [s] (the clock the agents' ``clock`` reads)."""
    episode: int = 0
    """Mission / episode counter: when it changes the agent forgets its neighbours and sightings."""

    @classmethod
    def new(cls, spec: SwarmSpec) -> "Perception":
        n, k = spec.n_agents, spec.arena.n_obstacles
        return cls(np.zeros(2), np.zeros(2), np.zeros((k, 2)), np.zeros(k), np.zeros(n, dtype=bool),
                   np.zeros((n, 2)), np.zeros((n, 2)))


StateSource = Callable[[int, Perception], bool]
CommandSink = Callable[[int, np.ndarray], None]
FaultHandler = Callable[[int, str], None]


@dataclass(frozen=True)
class AgentConfig:
    rate_hz: float | None = None
    """Control rate [Hz]; None: 1 / spec.timing.control_period."""
    phase_s: float = 0.0
    """Offset of this agent's ticks after the swarm's start [s]."""
    lead_s: float = 0.002
    """How long before its tick the agent prepares the observation and warms the actor [s]."""
    warm: bool = True
    """Run the actor once during the preparation (warm-up) so that the call at the tick is cache-hot."""
    reuse_observation: bool = True
    """With ``fast_encoder=False`` (the fast encoder costs less than this comparison): skip the encoder when
    every input it reads for this drone (belief positions and velocities, visibility, own sightings,
    obstacles, state timestamp) equals the last build's: the observation is then unchanged.
    A control rate above the state's update rate (100 Hz on a 10 Hz world, or on 50 Hz telemetry) hits this."""
    fast_encoder: bool = True
    """Build the observation with ``runtime.observation.OneObserverEncoder`` (numba, bit-identical to the training
    encoder); False: call ``encode_observations`` with ``B = 1`` (0.4-0.5 ms per build; the reference)."""
    deadline_s: float | None = None
    """A command published later than this after its tick is a deadline miss [s]; None: one period."""
    broadcast_period_s: float | None = None
    """Seconds between two broadcasts of own state and sightings; None: spec.timing.control_period (what
    training assumed: one message per control period, whatever the control rate)."""
    stale_after_s: float | None = None
    """Partial observability: a teammate is visible while heard within this [s]; None: 5 control periods.
    With full observability the last state heard is always used (ranges do not limit what is seen)."""
    record: int = 1 << 16
    """Ticks whose timings are kept (a ring); older ones are overwritten."""

    def period(self, spec: SwarmSpec) -> float:
        if self.rate_hz is None:
            return spec.timing.control_period
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise SpecError(f"agent.rate_hz: must be a finite number > 0, got {self.rate_hz!r}")
        return 1.0 / self.rate_hz


class AgentStats:
    """Counters and the timing ring of one agent."""

    def __init__(self, record: int) -> None:
        self.ticks = 0
        """Ticks whose command was published (actions, safe ones included)."""
        self.actions = 0
        """Ticks whose command came from the actor."""
        self.faults = 0
        self.last_fault = ""
        self.no_state = 0
        """Ticks with no fresh state from the source (safe action, counted as faults too)."""
        self.reused = 0
        """Ticks whose observation inputs had not changed since the last build (encoder skipped; only with
        ``AgentConfig.fast_encoder=False``)."""
        self.waiting = 0
        """Ticks spent waiting to hear every teammate once (full observability; safe action)."""
        self.deadline_misses = 0
        self.skipped = 0
        """Ticks not run because the loop fell more than a period behind (counted as misses too)."""
        self.tick_to_action = np.zeros(record)
        self.state_to_action = np.zeros(record)

    def timings(self) -> tuple[np.ndarray, np.ndarray]:
        """(tick_to_action, state_to_action) [s] of the recorded ticks."""
        n = min(self.ticks, self.tick_to_action.size)
        return self.tick_to_action[:n].copy(), self.state_to_action[:n].copy()

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("ticks", "actions", "faults", "last_fault", "no_state", "waiting",
                                              "reused", "deadline_misses", "skipped")}


_PR_SET_TIMERSLACK = 29


def precise_sleep_for_this_thread() -> bool:
    """Ask Linux for 1 us timer slack on the calling thread (the default 50 us delays every wake-up)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(_PR_SET_TIMERSLACK, 1000, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


class Agent:
    """One drone's runtime.

    >>> agent = Agent(i, spec, policy, source, sink, radio)        # doctest: +SKIP
    >>> agent.start(t0=clock()); ...; agent.stop()                  # its own thread at rate_hz
    >>> agent.tick()                                                # or one synchronous tick
    """

    def __init__(self, index: int, spec: SwarmSpec, policy, source: StateSource, sink: CommandSink,
                 radio: Radio | None = None, config: AgentConfig | None = None, clock: Clock = time.monotonic,
                 on_fault: FaultHandler | None = None) -> None:
        if not 0 <= index < spec.n_agents:
            raise SpecError(f"agent index {index} is outside the spec's {spec.n_agents} agents")
        self.index = index
        self.spec = spec
        self.role = spec.roles[index]
        self.agent_id = spec.team.agent_ids()[index]
        if getattr(policy, "role", self.role) != self.role:
            raise SpecError(f"agent {self.agent_id} flies as a {self.role.label}, its policy is a "
                            f"{Role(policy.role).label} actor: check the models' order")
        self.policy = policy
        self._warm = getattr(policy, "warm", None)
        self.source = source
        self.sink = sink
        self.radio = radio
        self.config = config or AgentConfig()
        self.clock = clock
        self.on_fault = on_fault
        self.period = self.config.period(spec)
        self.deadline = self.config.deadline_s if self.config.deadline_s is not None else self.period
        self.stale_after = (self.config.stale_after_s if self.config.stale_after_s is not None
                            else 5 * spec.timing.control_period)
        bp = self.config.broadcast_period_s
        self.broadcast_period = spec.timing.control_period if bp is None else bp
        self._next_broadcast = -math.inf
        self.stats = AgentStats(self.config.record)
        n, nt, e = spec.n_agents, spec.team.n_team, spec.team.n_evaders
        self.nt = nt
        self.in_team = index < nt
        self.full = spec.sensing.observability == "full"
        self._mates_sl = slice(0, nt) if self.in_team else slice(nt, n)
        self._others_sl = slice(nt, n) if self.in_team else slice(0, nt)
        self._all_heard = False
        # preallocated state
        self.perception = Perception.new(spec)
        self.neighbours = Neighbours(n)
        self._pos = np.zeros((1, n, 2))
        self._vel = np.zeros((1, n, 2))
        self._visible = np.zeros((1, n, n), dtype=bool)
        self._vis_row = self._visible[0, index]
        self._knowledge = np.zeros((1, nt, e, SIGHTING))
        self._knowledge[..., 4] = -np.inf
        self.sightings = self._knowledge[0, index] if self.in_team else None
        """This drone's target table [n_evaders, 5] (x, y, vx, vy, t_seen); None for evaders."""
        self._obst_pos = self.perception.obstacle_pos[None]
        self._obst_rad = self.perception.obstacle_radius[None]
        self._observers = np.array([index])
        self._obs_full = np.zeros((1, 1, spec.max_obs_dim))
        self.obs = self._obs_full[0, 0, :spec.obs_dim(self.role)]
        """The latest observation this agent built ([obs_dim] view into a preallocated buffer)."""
        self._encoder: OneObserverEncoder | None = None
        if self.config.fast_encoder:
            enc = OneObserverEncoder(spec, index)
            self._enc_in = (self._pos[0], self._vel[0], self.perception.obstacle_pos, self.perception.obstacle_radius,
                            self._knowledge[0])
            self._enc_out = self._obs_full[0, 0]
            enc.check(*self._enc_in, self._vis_row, self._enc_out)
            enc(*self._enc_in, 0.0, self._vis_row, self._enc_out)  # numba compiles (or loads its cache) here
            self._obs_full[:] = 0.0
            self._encoder = enc
        parts = [self._pos, self._vel, self.perception.obstacle_pos, self.perception.obstacle_radius,
                 self._vis_row] + ([self.sightings] if self.in_team else [])
        size = sum(a.size for a in parts) + 1
        self._sig, self._sig_new = np.zeros(size), np.zeros(size)
        self._sig_parts, o = [], 0
        for a in parts:
            self._sig_parts.append((self._sig_new[o:o + a.size], a))
            o += a.size
        self._sig_valid = False
        p = self.perception
        mt, ot = self._mates_sl, self._others_sl
        self._belief_args = (index, mt.start, mt.stop, ot.start, ot.stop, self.in_team, not self.full,
                             self.neighbours.pos, self.neighbours.vel, self.neighbours.t_recv, p.pos, p.vel,
                             p.others_pos, p.others_vel, p.sensed, self._pos[0], self._vel[0], self._vis_row,
                             self._knowledge[0, index if self.in_team else 0])
        _assemble_belief(*self._belief_args, 0.0, 0.0)  # compiled (or loaded from numba's cache) here
        self.action = np.zeros(2, dtype=np.float32)
        self.velocity = np.zeros(2)
        self._safe = np.zeros(2)
        self.max_speed = spec.role(self.role).max_speed
        self._max_speed = np.array([self.max_speed])
        self._epoch = 0  # the buffers start clean for episode 0
        self._ready = self._have_state = False
        self._t_state_read = 0.0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ------------------------------------------------------------------------------------ the steps
    def _fault(self, what: str) -> None:
        st = self.stats
        st.faults += 1
        st.last_fault = what
        if st.faults == 1 or st.faults % 1000 == 0:
            log.warning("%s: %s; safe action published (faults so far: %d)", self.agent_id, what, st.faults)
        if self.on_fault is not None:
            try:
                self.on_fault(self.index, what)
            except Exception:  # a broken fault handler must not take the loop down either
                log.exception("%s: fault handler failed", self.agent_id)

    def prepare(self) -> bool:
        """Read the state, drain the radio, update the sightings and build ``obs``. True when an action can
        be computed from it."""
        self._ready = self._have_state = False
        p = self.perception
        self._t_state_read = self.clock()
        if not self.source(self.index, p):
            self.stats.no_state += 1
            why = getattr(self.source, "why_not", None)
            self._fault("no fresh state from the state source" + (f": {why(self.index)}" if why is not None else ""))
            return False
        self._have_state = True
        if p.episode != self._epoch:
            self._new_epoch(p.episode)
        nb = self.neighbours
        if self.radio is not None:
            self.radio.poll(self._t_state_read, p.pos, nb, self.sightings)
        mt = self._mates_sl
        if self.full and not self._all_heard:
            heard = nb.t_state[mt] > -np.inf
            heard[self.index - mt.start] = True
            if not heard.all():
                self.stats.waiting += 1
                return False
            self._all_heard = True  # t_state only goes back to -inf with a new epoch
        # belief arrays, visibility, own sightings: one compiled call instead of a dozen numpy slice copies
        _assemble_belief(*self._belief_args, self._t_state_read - self.stale_after, p.time_s)
        if self._encoder is not None:  # building (~2 us) costs less than comparing the inputs (~7 us)
            self._encoder(*self._enc_in, p.time_s, self._vis_row, self._enc_out)
        elif not self._same_inputs(p.time_s):
            encode_observations(self.spec, self._pos, self._vel, self._obst_pos, self._obst_rad, self._knowledge,
                                p.time_s, observers=self._observers, visible=self._visible, out=self._obs_full)
        else:
            self.stats.reused += 1
        if self.config.warm:
            if self._warm is not None:
                self._warm()  # the network on its last input: weights and code back in the caches, no checks
            else:
                self.policy.act(self.obs, out=self.action)
        self._ready = True
        return True

    def _same_inputs(self, time_s: float) -> bool:
        """Whether everything the encoder reads for this drone equals what it read at the last build (then
        the observation, a pure function of it, is still in ``obs``); records the new inputs otherwise."""
        if not self.config.reuse_observation:
            return False
        new, old = self._sig_new, self._sig
        for dst, src in self._sig_parts:
            dst[:] = src.reshape(-1)
        new[-1] = time_s
        if self._sig_valid and np.array_equal(new, old):
            return True
        old[:] = new
        self._sig_valid = True
        return False

    def actuate(self, tick: float | None = None) -> None:
        """Run the actor on ``obs`` (or keep the safe action when ``prepare`` failed), publish the command,
        record the timing against ``tick`` (default: now), then broadcast this drone's state."""
        st = self.stats
        v = self.velocity
        if self._ready:
            faults = self.policy.faults
            self.policy.act(self.obs, out=self.action)
            if self.policy.faults != faults:
                self._fault(f"policy: {self.policy.last_fault}")
            action_to_velocity(self._max_speed, self.action[None], out=v[None])
            st.actions += 1
        else:
            v[:] = 0.0
        self.sink(self.index, v)
        done = self.clock()
        k = st.ticks % st.tick_to_action.size
        lat = done - (done if tick is None else tick)
        st.tick_to_action[k] = lat
        st.state_to_action[k] = done - self._t_state_read
        if lat > self.deadline:
            st.deadline_misses += 1
        st.ticks += 1
        if self._have_state and self.radio is not None and done >= self._next_broadcast:
            p = self.perception
            self.radio.broadcast(done, p.time_s, p.pos, p.vel, self.sightings)
            # the next one a period on, with half a tick of slack so that it lands on the matching tick
            self._next_broadcast = max(self._next_broadcast + self.broadcast_period,
                                       done + self.broadcast_period - 0.5 * self.period)

    def tick(self) -> np.ndarray:
        """One synchronous tick (prepare, act, publish, broadcast); returns the published velocity."""
        t = self.clock()
        self._guarded(self.prepare)
        self._guarded_actuate(t)
        return self.velocity

    def _new_epoch(self, epoch: int) -> None:
        self._epoch = epoch
        self._all_heard = False
        self._sig_valid = False
        self.neighbours.reset()
        self._knowledge[..., :4] = 0.0
        self._knowledge[..., 4] = -np.inf
        if self.radio is not None:
            self.radio.clear(epoch)

    def _guarded(self, step: Callable[[], object]) -> None:
        try:
            step()
        except Exception as exc:  # one drone's fault must never stop its loop or the swarm
            self._ready = False
            self._fault(f"{type(exc).__name__}: {exc}")

    def _guarded_actuate(self, tick: float) -> None:
        try:
            self.actuate(tick)
        except Exception as exc:
            self._ready = False
            self._fault(f"{type(exc).__name__}: {exc}")
            try:
                self.velocity[:] = 0.0
                self.sink(self.index, self._safe)
            except Exception as exc2:
                self._fault(f"command sink failed with the safe action: {type(exc2).__name__}: {exc2}")

    # ------------------------------------------------------------------------------------ the thread
    def _sleep_until(self, t: float) -> bool:
        """Sleep until clock() >= t; True when stop was requested."""
        while True:
            rest = t - self.clock()
            if rest <= 0:
                return self._stop.is_set()
            if rest > 0.05:
                if self._stop.wait(0.05):
                    return True
            else:
                time.sleep(rest)

    def _loop(self, t0: float) -> None:
        precise_sleep_for_this_thread()
        period, lead = self.period, self.config.lead_s
        tick = t0 + self.config.phase_s
        late = self.clock() - (tick - lead)
        if late > 0:  # started after its first tick (a slow process start): begin at the next one, no miss
            tick += math.ceil(late / period) * period
        st = self.stats
        while True:
            if self._sleep_until(tick - lead):
                break
            self._guarded(self.prepare)
            if self._sleep_until(tick):
                break
            self._guarded_actuate(tick)
            tick += period
            behind = self.clock() - tick
            if behind > 0:  # overran a whole period: skip the ticks that are already past
                n = int(behind // period) + 1
                st.skipped += n
                st.deadline_misses += n
                tick += n * period

    def start(self, t0: float | None = None) -> None:
        """Start the loop on its own thread; ticks at ``t0 + phase_s + k / rate_hz`` (t0 default: now)."""
        if self._thread is not None:
            raise RuntimeError(f"{self.agent_id}: already started")
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, args=(self.clock() if t0 is None else t0,),
                                        name=f"agent-{self.agent_id}", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> bool:
        """Stop the loop and publish the safe action; True when the thread ended within ``timeout``."""
        self._stop.set()
        ok = True
        if self._thread is not None:
            self._thread.join(timeout)
            ok = not self._thread.is_alive()
            self._thread = None
        try:
            self.sink(self.index, self._safe)
        except Exception as exc:
            self._fault(f"command sink failed with the safe action at stop: {type(exc).__name__}: {exc}")
        return ok

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()


@njit(cache=True)
def _assemble_belief(index: int, m0: int, m1: int, o0: int, o1: int, in_team: bool, partial: bool,
                     nb_pos: np.ndarray, nb_vel: np.ndarray, nb_t_recv: np.ndarray, own_pos: np.ndarray,
                     own_vel: np.ndarray, others_pos: np.ndarray, others_vel: np.ndarray, sensed: np.ndarray,
                     pos: np.ndarray, vel: np.ndarray, vis: np.ndarray, sightings: np.ndarray, heard_after: float,
                     time_s: float) -> None:
    """What the drone believes: own team [m0, m1) from its radio, itself from its own state, the other team
    [o0, o1) from its sensors; with partial observability a teammate is visible when heard at or after
    ``heard_after`` and the other team when sensed; own sensing overrides the pursuer team's sightings."""
    for j in range(m0, m1):
        pos[j, 0] = nb_pos[j, 0]
        pos[j, 1] = nb_pos[j, 1]
        vel[j, 0] = nb_vel[j, 0]
        vel[j, 1] = nb_vel[j, 1]
    pos[index, 0] = own_pos[0]
    pos[index, 1] = own_pos[1]
    vel[index, 0] = own_vel[0]
    vel[index, 1] = own_vel[1]
    for j in range(o0, o1):
        pos[j, 0] = others_pos[j, 0]
        pos[j, 1] = others_pos[j, 1]
        vel[j, 0] = others_vel[j, 0]
        vel[j, 1] = others_vel[j, 1]
    if partial:
        for j in range(m0, m1):
            vis[j] = nb_t_recv[j] >= heard_after
        for j in range(o0, o1):
            vis[j] = sensed[j]
    if in_team:
        for j in range(o0, o1):
            if sensed[j]:
                e = j - o0
                sightings[e, 0] = others_pos[j, 0]
                sightings[e, 1] = others_pos[j, 1]
                sightings[e, 2] = others_vel[j, 0]
                sightings[e, 3] = others_vel[j, 1]
                sightings[e, 4] = time_s


def staggered(n: int, period: float, spread: float = 1.0) -> list[float]:
    """Phases that spread ``n`` agents evenly over ``spread`` of a period."""
    return [spread * period * i / n for i in range(n)]


__all__ = ["Agent", "AgentConfig", "AgentStats", "Perception", "StateSource", "CommandSink", "FaultHandler",
           "staggered", "precise_sleep_for_this_thread"]
