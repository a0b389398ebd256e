"""The runtime against the simulated world: one env of ``runtime.world`` in real time, one agent per drone.

The world runs in its own process and publishes its state on a ``WorldBoard`` (a seqlock-protected block of
shared memory: time, episode, positions, velocities, obstacles, and one command row per drone), stepping
every ``spec.timing.control_period`` with the latest commands and scoring the run with
``runtime.metrics``. The agents read their state from the board (``WorldSource``: own state, the obstacle
map, and what their own sensors see) and write their commands to it (``WorldSink``) - the same two
callables a ground station plugs its links into. Agents run as threads of this process with an
``InProcessBus`` (``processes=False``), or each in its own process talking over ``UdpTransport`` on
loopback (``processes=True``), as on separate onboard computers.

Keeping the world out of the agents' process keeps its steps and the metrics' raster work from holding the
agents' interpreter lock at their ticks.
"""
from __future__ import annotations

import logging
import math
import multiprocessing as mp
import os
import queue
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.agent import Agent, AgentConfig, staggered
from runtime.comms import CommConfig, CommStats, InProcessBus, Radio, UdpTransport, free_udp_ports
from runtime.observation import OneObserverEncoder
from runtime.spec import ENGINES, SpecError, SwarmSpec
from runtime.world_board import MP_CONTEXT, WorldBoard, WorldSink, WorldSource

log = logging.getLogger(__name__)

_CTX = MP_CONTEXT
PROCESS_START_TIMEOUT_S = 120.0
"""With processes: how long the world and the agent processes may take to be built before the run is called
off [s] (loading models and compiling numba takes seconds each on a cold, busy machine)."""


# --------------------------------------------------------------------------------------------------
# the world process


def _await_start(start: "StartGate | None", t0: float, t_end: float, ready: "mp.Queue | None",
                 who: str) -> tuple[float, float] | None:
    """In process mode, report ``who`` ready and wait for the parent's start time (None: the run was called
    off); in-process, (t0, t_end) as given."""
    if start is None:
        return t0, t_end
    ready.put(who)
    return start.wait()


class StartGate:
    """The start of a run with processes: each process reports ready once it is built (models loaded, numba
    compiled, sockets bound), and the clock starts when all have, so that a slow start on a busy machine
    delays the run instead of faulting agents that were still loading."""

    def __init__(self, ctx) -> None:
        self._times = ctx.Array("d", 2)
        self._go = ctx.Event()

    def open(self, t0: float, t_end: float) -> None:
        self._times[0], self._times[1] = t0, t_end
        self._go.set()

    def call_off(self) -> None:
        self._times[0] = self._times[1] = float("nan")
        self._go.set()

    def wait(self, timeout: float = 600.0) -> tuple[float, float] | None:
        if not self._go.wait(timeout):
            return None
        t0, t_end = self._times[0], self._times[1]
        return None if t0 != t0 else (t0, t_end)


def _world_main(board_name: str, spec_dict: dict, seed: int, t0: float, t_end: float, out: mp.Queue,
                start: StartGate | None = None, ready: "mp.Queue | None" = None) -> None:
    from runtime.metrics import MetricsAccumulator, summarize
    from runtime.world import World
    try:
        spec = SwarmSpec.from_dict(spec_dict)
        board = WorldBoard(spec, name=board_name)
        world = World(spec, 1, seed)
        s = world.reset()
        metrics = MetricsAccumulator(spec, 1)
        metrics.begin_episodes(np.array([0]), s.obstacle_pos, s.obstacle_radius)
        episode = 0
        dt = spec.timing.control_period
        steps = 0
        late = []
        act = np.zeros((1, spec.n_agents, 2))
        times = _await_start(start, t0, t_end, ready, "world")
        if times is None:
            return
        t0, t_end = times
        board.publish(s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], time.monotonic(), episode)
        nxt = t0 + dt
        while nxt <= t_end and not board.stopped:
            rest = nxt - time.monotonic()
            if rest > 0:
                time.sleep(rest)
            late.append(time.monotonic() - nxt)
            act[0] = board.cmd
            contacts = world.step(act)
            metrics.update(s.pos, contacts, world.obstacle_contacts(), world.last_distances)
            steps += 1
            if s.step[0] >= spec.timing.episode_steps:
                metrics.end_episodes(np.array([0]))
                world.reset()
                metrics.begin_episodes(np.array([0]), s.obstacle_pos, s.obstacle_radius)
                episode += 1
            board.publish(s.pos[0], s.vel[0], s.obstacle_pos[0], s.obstacle_radius[0], time.monotonic(), episode)
            nxt += dt
        partial = int(s.step[0])
        if partial:
            metrics.end_episodes(np.array([0]))
        res = summarize(metrics.records)
        res.update(steps=steps, partial_last_episode_steps=partial,
                   world_step_late_p99_ms=float(np.percentile(late, 99) * 1e3) if late else 0.0,
                   nonfinite_actions=world.nonfinite_actions)
        board.close()
        out.put(("world", res))
    except Exception as exc:  # reported to the parent, which prints it
        out.put(("world-error", f"{type(exc).__name__}: {exc}"))


# --------------------------------------------------------------------------------------------------
# agents


@dataclass(frozen=True)
class RunConfig:
    duration_s: float = 30.0
    rate_hz: float | None = None
    """Agents' control rate [Hz]; None: 1 / spec.timing.control_period (the world always steps at that)."""
    comms: CommConfig = field(default_factory=CommConfig)
    processes: bool = False
    seed: int = 0
    stagger: bool = True
    """Spread the agents' ticks evenly over the period."""
    lead_s: float | None = None
    """Preparation lead before each tick [s]; None: min(2 ms, a quarter period)."""
    warm: bool = True
    reuse_observation: bool = True
    """Skip the encoder when a drone's inputs have not changed (``AgentConfig.reuse_observation``)."""
    fast_encoder: bool = True
    """Build observations with the one-observer numba encoder (``AgentConfig.fast_encoder``); False: the batched
    training encoder with B = 1 (the reference, ~0.4 ms per build)."""
    switch_interval_s: float | None = 1e-4
    """``sys.setswitchinterval`` for the agents' process (threads mode): how long a waking agent can wait
    for another thread's interpreter lock; None keeps Python's 5 ms."""
    startup_s: float = 0.5
    """Delay before the first tick [s]: after launching the agents (threads), or after every process has
    reported ready (processes: ``StartGate``)."""
    engine: str = "onnxruntime"
    """How each actor runs (``runtime.spec.ENGINES``): onnxruntime, or the compiled MLP proved equal to it."""

    def __post_init__(self) -> None:
        if not (self.duration_s > 0 and math.isfinite(self.duration_s)):
            raise SpecError(f"run.duration_s: must be a finite number > 0, got {self.duration_s!r}")
        if self.rate_hz is not None and not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise SpecError(f"run.rate_hz: must be a finite number > 0, got {self.rate_hz!r}")
        if self.engine not in ENGINES:
            raise SpecError(f"run.engine: must be 'onnxruntime' or 'compiled', got {self.engine!r}")


def _agent_config(spec: SwarmSpec, cfg: RunConfig, index: int) -> AgentConfig:
    period = 1.0 / cfg.rate_hz if cfg.rate_hz else spec.timing.control_period
    phase = staggered(spec.n_agents, period)[index] if cfg.stagger else 0.0
    lead = cfg.lead_s if cfg.lead_s is not None else min(0.002, period / 4)
    return AgentConfig(rate_hz=1.0 / period, phase_s=phase, lead_s=lead, warm=cfg.warm,
                       reuse_observation=cfg.reuse_observation, fast_encoder=cfg.fast_encoder,
                       record=max(16, int(cfg.duration_s / period) + 16))


def _agent_result(agent: Agent, radio: Radio | None) -> dict:
    tta, sta = agent.stats.timings()
    return {"index": agent.index, "stats": agent.stats.as_dict(), "tick_to_action": tta, "state_to_action": sta,
            "comms": radio.stats.as_dict() if radio is not None else {},
            "policy_faults": agent.policy.faults}


def _agent_main(index: int, models: str, board_name: str, ports: list[int], cfg: RunConfig, t0: float,
                t_end: float, out: mp.Queue, start: StartGate | None = None, ready: "mp.Queue | None" = None) -> None:
    from runtime.policy import load_models
    try:
        manifest, (pol,) = load_models(models, agents=[index], engine=cfg.engine)
        spec = manifest.spec
        board = WorldBoard(spec, name=board_name)
        radio = Radio(spec, index, UdpTransport(index, ports), cfg.comms)
        agent = Agent(index, spec, pol, WorldSource(board, spec), WorldSink(board, spec), radio,
                      _agent_config(spec, cfg, index))
        pol.act(agent.obs, out=agent.action)  # onnxruntime's first call, before the clock
        agent.action[:] = 0.0
        times = _await_start(start, t0, t_end, ready, f"agent {index}")
        if times is None:
            radio.close()
            board.close()
            return
        t0, t_end = times
        agent.start(t0)
        while time.monotonic() < t_end and not board.stopped:
            time.sleep(min(0.05, max(0.0, t_end - time.monotonic())))
        agent.stop()
        radio.close()
        res = _agent_result(agent, radio)
        res["rss_kib"] = _rss_kib()
        board.close()
        out.put(("agent", res))
    except Exception as exc:
        out.put(("agent-error", f"agent {index}: {type(exc).__name__}: {exc}"))


def _rss_kib() -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return -1


def _check_files(manifest) -> None:
    from runtime.policy import _FIX, ModelCorrupted, ModelNotFound, _sha256
    for e in manifest.agents:
        if not e.file.is_file():
            raise ModelNotFound(f"no ONNX model at {str(e.file)!r}: {_FIX}")
        got = _sha256(e.file)
        if got != e.sha256:
            raise ModelCorrupted(f"{str(e.file)!r} has sha256 {got[:12]}..., the manifest says {e.sha256[:12]}...: "
                                 f"the file was damaged or replaced; {_FIX}")


def run_swarm(models: str | Path, cfg: RunConfig) -> dict:
    """Run every agent of a models folder against one real-time world for ``cfg.duration_s``; returns the
    metrics (``runtime.metrics.METRIC_KEYS``), the loop timings and the comms counters. Raises
    ``runtime.policy.PolicyError`` for a bad models folder."""
    from runtime.policy import load_models, read_manifest
    if cfg.processes:
        manifest = read_manifest(models)
        _check_files(manifest)  # each agent process loads its own model; fail here, with the named error
        policies = None
    else:
        manifest, policies = load_models(models, engine=cfg.engine)
    spec = manifest.spec
    n = spec.n_agents
    if cfg.fast_encoder:  # numba's compile or cache load (0.5-4 s), before the clock and the CPU count start
        OneObserverEncoder(spec, 0).compile()
    board = WorldBoard(spec, shared=True)
    results: "mp.Queue" = _CTX.Queue()
    procs: list[mp.process.BaseProcess] = []
    agents: list[Agent] = []
    radios: list[Radio] = []
    old_switch = sys.getswitchinterval()
    load_before = os.getloadavg()[0]
    cpu_before = time.process_time()
    try:
        start = time.monotonic() + cfg.startup_s
        t_end = start + cfg.duration_s
        gate = StartGate(_CTX) if cfg.processes else None
        ready: "mp.Queue | None" = _CTX.Queue() if cfg.processes else None
        world = _CTX.Process(target=_world_main, args=(board.name, spec.to_dict(), cfg.seed, start, t_end, results,
                                                        gate, ready), name="swarm-world", daemon=True)
        world.start()
        procs.append(world)
        if cfg.processes:
            ports = free_udp_ports(n)
            for i in range(n):
                p = _CTX.Process(target=_agent_main, args=(i, str(models), board.name, ports, cfg, start, t_end,
                                                           results, gate, ready), name=f"swarm-agent-{i}",
                                 daemon=True)
                p.start()
                procs.append(p)
            # the clock starts when the world and every agent process are built (a busy machine only waits)
            waiting, deadline = n + 1, time.monotonic() + PROCESS_START_TIMEOUT_S
            while waiting and time.monotonic() < deadline:
                try:
                    ready.get(timeout=0.5)
                    waiting -= 1
                except queue.Empty:
                    if not all(p.is_alive() for p in procs):
                        break
            if waiting:
                gate.call_off()
                try:
                    kind, val = results.get(timeout=5.0)
                    why = val if kind.endswith("error") else "a process ended before it was ready"
                except queue.Empty:
                    why = f"{waiting} of {n + 1} processes were not ready after {PROCESS_START_TIMEOUT_S:.0f} s"
                raise RuntimeError(f"the run did not start: {why}")
            start = time.monotonic() + cfg.startup_s
            t_end = start + cfg.duration_s
            gate.open(start, t_end)
        else:
            if cfg.switch_interval_s is not None:
                sys.setswitchinterval(cfg.switch_interval_s)
            bus = InProcessBus(n)
            source, sink = WorldSource(board, spec), WorldSink(board, spec)
            for i in range(n):
                radio = Radio(spec, i, bus.endpoint(i), cfg.comms)
                radios.append(radio)
                agents.append(Agent(i, spec, policies[i], source, sink, radio, _agent_config(spec, cfg, i)))
            for a in agents:
                a.start(start)
            rss = _rss_kib()
            while time.monotonic() < t_end:
                time.sleep(min(0.1, max(0.0, t_end - time.monotonic())))
            for a in agents:
                a.stop()
            rss = max(rss, _rss_kib())
        world_res, agent_res, errors = None, [], []
        want = 1 + (n if cfg.processes else 0)
        deadline = time.monotonic() + 30.0 + (5.0 * n if cfg.processes else 0.0)
        while want and time.monotonic() < deadline:
            try:
                kind, val = results.get(timeout=0.5)
            except queue.Empty:
                if not any(p.is_alive() for p in procs):
                    break
                continue
            want -= 1
            if kind == "world":
                world_res = val
            elif kind == "agent":
                agent_res.append(val)
            else:
                errors.append(val)
        if errors or world_res is None:
            raise RuntimeError("; ".join(errors) or "the world process ended without a result")
        if not cfg.processes:
            agent_res = [_agent_result(a, r) for a, r in zip(agents, radios)]
            rss_kib = rss
        else:
            if len(agent_res) != n:
                raise RuntimeError(f"only {len(agent_res)} of {n} agent processes reported")
            rss_kib = sum(r["rss_kib"] for r in agent_res)
        res = _summarize(spec, cfg, world_res, agent_res, rss_kib)
        res["host_load_avg_1min"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
        if not cfg.processes:
            res["agents_cpu_s"] = round(time.process_time() - cpu_before, 2)
        return res
    finally:
        sys.setswitchinterval(old_switch)
        board.request_stop()
        for a in agents:
            if a.running:
                a.stop()
        for p in procs:
            p.join(5.0)
            if p.is_alive():
                p.terminate()
                p.join(1.0)
        for r in radios:
            r.close()
        board.close(unlink=True)


def _pct(x: np.ndarray, q: float) -> float:
    return float(np.percentile(x, q) * 1e6) if x.size else float("nan")


def _summarize(spec: SwarmSpec, cfg: RunConfig, world: dict, agents: list[dict], rss_kib: int) -> dict:
    agents = sorted(agents, key=lambda r: r["index"])
    tta = np.concatenate([r["tick_to_action"] for r in agents])
    sta = np.concatenate([r["state_to_action"] for r in agents])
    comms = CommStats()
    for r in agents:
        if r["comms"]:
            comms.add(CommStats(**r["comms"]))
    tot = lambda k: int(sum(r["stats"][k] for r in agents))  # noqa: E731
    out = dict(world)
    out.update({
        "tick_to_action_p50_us": _pct(tta, 50), "tick_to_action_p99_us": _pct(tta, 99),
        "tick_to_action_max_us": float(tta.max() * 1e6) if tta.size else float("nan"),
        "state_to_action_p50_us": _pct(sta, 50), "state_to_action_p99_us": _pct(sta, 99),
        "state_to_action_max_us": float(sta.max() * 1e6) if sta.size else float("nan"),
        "deadline_misses": tot("deadline_misses"), "skipped_ticks": tot("skipped"), "agent_ticks": tot("ticks"),
        "agent_faults": tot("faults"), "waiting_ticks": tot("waiting"), "no_state_ticks": tot("no_state"),
        "reused_observations": tot("reused"),
        "comms": comms.as_dict(),
        "faults_by_agent": {spec.team.agent_ids()[r["index"]]: r["stats"]["last_fault"]
                            for r in agents if r["stats"]["faults"]},
        "rss_mib": round(rss_kib / 1024.0, 1) if rss_kib > 0 else None,
        "config": {"duration_s": cfg.duration_s, "rate_hz": cfg.rate_hz or 1.0 / spec.timing.control_period,
                   "processes": cfg.processes, "engine": cfg.engine, "loss": cfg.comms.loss,
                   "latency_s": cfg.comms.latency_s, "exact_values": cfg.comms.exact_values,
                   "bandwidth_bps": cfg.comms.bandwidth_bps, "comm_range": cfg.comms.range_for(spec),
                   "seed": cfg.seed, "stagger": cfg.stagger, "warm": cfg.warm,
                   "reuse_observation": cfg.reuse_observation, "agents": spec.n_agents,
                   "spec_hash": spec.hash, "observability": spec.sensing.observability,
                   "cpus": os.cpu_count()},
    })
    return out


__all__ = ["WorldBoard", "WorldSource", "WorldSink", "RunConfig", "run_swarm"]
