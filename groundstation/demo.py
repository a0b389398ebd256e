"""``swarm-gs demo``: the whole stack against 12 simulated Crazyflies.

Twelve simulated Crazyflies (``groundstation.sim.SimSwarm``: CRTP over UDP; in a process of their own,
``groundstation.sim.remote.SimProcess``, unless ``sim_in_process``) are connected through unmodified
cflib (``udp://`` URIs, ``CflibLink``); 10 form the pursuer team (pursuer and scout actors) and 2 fly the
evader actors. The arena's three obstacles are drawn from the spec with the seed (``runtime.world``) and
become keep-out circles of the fence (the simulator has no physical obstacles, so the fence is what keeps
drones out of them). Preflight, role assignment, staggered takeoff, the mission flown by the exported actors
(``mission.AgentPilot``: one ``runtime.agent.Agent`` per actor), landing; then the paper's metrics
(``runtime.metrics``, one episode per ``spec.timing.episode_steps`` control periods), link statistics, a
JSON-lines flight log and a picture. What is measured during the flight is in ``demo_metrics`` (the paper's
metrics take their distances and contacts from a ``runtime.world.World`` holding the measured positions, so
they count contacts as evaluation does), the result dict, summary and picture in ``demo_report``.

Separation: every setpoint passes the separation filter (``groundstation.separation``) unless
``separation=False`` (``--no-separation``, for comparisons only). The simulated drones crash when two touch;
the results count those contacts (``drone_contacts``), the closest two airborne drones came (ground truth,
``min_pair_distance``) and how often a pair came closer than ``min_distance``. A capture is a pursuer-team
drone within ``capture_distance`` of an evader, never contact.

Failure injection: ``kill_link = (drone, t)`` makes that simulated drone stop answering ``t`` s into the
mission; ``loss = p`` drops every datagram in either direction with probability ``p`` (a relay between cflib
and the simulators) once the links are up. cflib's UDP driver does not retransmit, so a lost table-of-contents
request would stall the connection; a Crazyradio retransmits at its link layer, and what ``loss`` models is
what is still lost after that: setpoints, telemetry samples and high-level commands (the session repeats land
commands until the drone reports landed).
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import logging
import math
import random
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from groundstation.demo_metrics import LANDED_Z, EpisodeMetrics, PairMonitor, on_ground
from groundstation.demo_report import format_summary, plot_flight, results, separation_results
from groundstation.fence import FenceArenaMismatch, check_arena
from groundstation.flight import FlightConfig, FlightSession, close_links
from groundstation.link import LinkError, open_link
from groundstation.mission import AgentPilot
from groundstation.positioning import AnchorLayout
from groundstation.roles import EVADER_TEAM, PURSUER_TEAM
from groundstation.safety import FenceConfig, KeepOut, in_safe_set
from groundstation.separation import SeparationConfig
from groundstation.sim.relay import LossyRelay
from groundstation.sim.remote import SimProcess
from groundstation.sim.swarm import SimSwarm, free_base_port
from runtime.cliutil import json_safe, write_text_atomic
from runtime.policy import load_models, read_manifest
from runtime.spec import SwarmSpec, load_toml

__all__ = ["LANDED_Z", "RESULT_KEYS", "DemoError", "DemoInterrupted", "DemoOptions", "EpisodeMetrics", "LossyRelay",
           "PairMonitor", "draw_obstacles", "format_summary", "plot_flight", "run_demo", "start_positions"]

log = logging.getLogger(__name__)

RESULT_KEYS = ("mean_min_dist", "mean_avg_dist", "mean_max_dist", "tracking_rate", "coverage",
               "collisions_per_episode", "episodes", "landed", "geofence_violations", "setpoint_latency_p99_ms",
               "drone_contacts", "min_pair_distance", "pairs_below_min_distance", "separation")
PAIR_PERIOD_S = 0.02
"""How often the demo samples the simulators' ground truth for the closest pair [s] (one message to the
simulators' process; the simulator itself counts every contact at 10 ms)."""
METRICS_PERIOD = 1.0
"""How often the demo writes the metrics so far to the flight log (an ``event: metrics`` row) [s]."""


class DemoError(RuntimeError):
    """The demo cannot run; the message says how to fix it."""


class DemoInterrupted(KeyboardInterrupt):
    """Ctrl-C during the demo, after the session landed everyone it could reach."""

    def __init__(self, statuses: dict[str, str], on_ground: int) -> None:
        self.statuses, self.on_ground = statuses, on_ground
        summary = ", ".join(f"{d} {s}" for d, s in statuses.items())
        super().__init__(f"{on_ground} of {len(statuses)} drones on the ground with motors off ({summary})")


@dataclass(frozen=True)
class DemoOptions:
    duration: float = 30.0
    """Mission time [s] (after takeoff, before landing)."""
    speed: float = 1.0
    """Multiplier on the policies' velocity commands."""
    kill_link: tuple[str, float] | None = None
    """(drone id or index, seconds into the mission) at which that drone's link is cut."""
    loss: float = 0.0
    """Probability of losing each datagram, both directions."""
    models: str = "models/role_based"
    engine: str = "onnxruntime"
    """How the actors run: "onnxruntime" or "compiled" (``runtime.spec.ENGINES``)."""
    spec: str | None = None
    """TOML whose [spec] table is the spec the ground station encodes observations for (None: the spec the
    models were trained on, from their manifest; a given one must match it, preflight checks)."""
    fence: str = "configs/fence.toml"
    anchors: str = "configs/lps_anchors.toml"
    flight: str | None = None
    """TOML with a [flight] table overriding ``FlightConfig``."""
    seed: int = 0
    json_path: str | None = None
    log_path: str | None = None
    plot_path: str | None = None
    base_port: int | None = None
    telemetry_period_ms: int = 20
    separation: bool = True
    """False: fly without the separation filter (``--no-separation``), for comparisons only. The
    ``[separation]`` table of ``flight`` (when given) sets the filter's parameters."""
    sim_in_process: bool = False
    """True: the simulated Crazyflies in the ground station's interpreter (``--sim-in-process``; they then share
    its GIL, and its stalls pause their world). Default: a process of their own (``SimProcess``), as real drones
    are, talking CRTP over UDP."""
    separation_process: bool = True
    """The separation filter's joint solve in a process of its own (``JointFilter(process=True)``); False: in a
    thread of the ground station's interpreter (for comparison, ``tests/benchmarks/test_bench_demo_latency.py``)."""
    view_port: int | None = None
    """Serve the live view (``groundstation.liveview``) on this port during the flight (``--view``); None: no
    view, 0: any free port."""


# ---- setup ---------------------------------------------------------------------------------------

def draw_obstacles(spec: SwarmSpec, seed: int) -> np.ndarray:
    """[K, 3] obstacles (x, y, radius) [m] drawn like a training episode's (``runtime.world``)."""
    from runtime.world import World
    w = World(spec, n_envs=1, seed=seed)
    s = w.reset()
    return np.concatenate([s.obstacle_pos[0], s.obstacle_radius[0, :, None]], axis=1)


def start_positions(fence: FenceConfig, n: int, seed: int, spacing: float = 0.7, clearance: float = 0.3) -> np.ndarray:
    """[n, 3] ground positions inside the fence's safe area, ``clearance`` [m] further from its edges and
    keep-outs, at least ``spacing`` [m] apart, drawn from a grid with ``seed``."""
    lo, hi = fence.bounds()
    z = fence.z_band[0]
    step = spacing / 2.0
    xs = np.arange(lo[0] + step, hi[0], step)
    ys = np.arange(lo[1] + step, hi[1], step)
    cands = []
    for x in xs:
        for y in ys:
            near = [(x + dx, y + dy, z) for dx, dy in ((clearance, 0), (-clearance, 0), (0, clearance),
                                                       (0, -clearance), (0, 0))]
            if all(in_safe_set(fence, p) for p in near):
                cands.append((x, y))
    rng = random.Random(seed)
    rng.shuffle(cands)
    chosen: list[tuple[float, float]] = []
    for c in cands:
        if all(math.hypot(c[0] - o[0], c[1] - o[1]) >= spacing for o in chosen):
            chosen.append(c)
            if len(chosen) == n:
                return np.array([[x, y, 0.0] for x, y in chosen])
    raise DemoError(f"cannot place {n} drones {spacing} m apart inside the fence's safe area: enlarge the fence "
                    f"or use fewer obstacles")


# ---- the run -------------------------------------------------------------------------------------

def _resolve_drone(token: str, ids: list[str]) -> str:
    if token in ids:
        return token
    try:
        i = int(token)
    except ValueError:
        raise DemoError(f"--kill-link: unknown drone {token!r}; use an index 0..{len(ids) - 1} or an id "
                        f"({ids[0]} ... {ids[-1]})") from None
    if not 0 <= i < len(ids):
        raise DemoError(f"--kill-link: drone index {i} out of range 0..{len(ids) - 1}")
    return ids[i]


def _open_links(uris: list[str], period_ms: int, link_loss_timeout: float) -> list:
    from groundstation.fleet import TOC_CACHE  # shared with swarm-gs fly: the next demo skips the TOC download
    with concurrent.futures.ThreadPoolExecutor(len(uris)) as ex:
        futures = [ex.submit(open_link, u, period_ms=period_ms, rw_cache=str(TOC_CACHE),
                             link_loss_timeout=link_loss_timeout)
                   for u in uris]
        links, errors = [], []
        for f in futures:
            try:
                links.append(f.result())
            except LinkError as exc:
                errors.append(str(exc))
    if errors:
        close_links(links)
        raise DemoError("cannot connect to the simulated drones:\n" + "\n".join(errors))
    return links


def run_demo(opts: DemoOptions, echo: Callable[[str], None] | None = None, view=None) -> dict[str, Any]:
    """Fly the demo; returns the results (``RESULT_KEYS`` and more), also written to ``opts.json_path``.
    ``echo`` gets the progress lines (the live view's address); by default they are logged. ``view``: a started
    ``liveview.LiveView`` to show the flight in (the caller stops it); else ``opts.view_port`` starts one for the
    flight (a taken port is a ``DemoError`` before any simulator starts)."""
    echo = echo or (lambda line: log.info("%s", line))
    if not 0.0 <= opts.loss < 1.0:
        raise DemoError(f"--loss: must be in [0, 1), got {opts.loss}")
    if not (opts.duration > 0 and math.isfinite(opts.duration)):
        raise DemoError(f"--duration: must be > 0 s, got {opts.duration}")
    if not (opts.speed > 0 and math.isfinite(opts.speed)):
        raise DemoError(f"--speed: must be > 0, got {opts.speed}")
    manifest = read_manifest(opts.models)  # ModelNotFound / ModelCorrupted say how to export
    spec = SwarmSpec.from_toml(opts.spec) if opts.spec else manifest.spec  # the team flown is the models'
    flight_cfg = FlightConfig.from_toml(opts.flight) if opts.flight else FlightConfig()
    flight_cfg = dataclasses.replace(flight_cfg, speed_scale=flight_cfg.speed_scale * opts.speed)
    separation = SeparationConfig.from_dict(load_toml(opts.flight).get("separation", {})) if opts.flight \
        else SeparationConfig()
    separation = dataclasses.replace(separation, enabled=separation.enabled and opts.separation)
    obstacles = draw_obstacles(spec, opts.seed)
    fence = FenceConfig.from_toml(opts.fence, spec=manifest.spec)
    try:  # before any simulator starts
        check_arena(fence, manifest.spec, f"fence {opts.fence}", f"the models in {opts.models}")
    except FenceArenaMismatch as exc:
        raise DemoError(str(exc)) from None
    fence = dataclasses.replace(fence, keep_out=tuple(KeepOut(float(x), float(y), float(r)) for x, y, r in obstacles))
    anchors = AnchorLayout.from_toml(opts.anchors, fence=fence)
    n = spec.n_agents
    ids = [f"cf{i}" for i in range(n)]
    teams = {d: (EVADER_TEAM if i >= spec.team.n_team else PURSUER_TEAM) for i, d in enumerate(ids)}
    kill = None if opts.kill_link is None else (_resolve_drone(str(opts.kill_link[0]), ids), float(opts.kill_link[1]))
    base = opts.base_port if opts.base_port is not None else free_base_port(n, seed=opts.seed)
    starts = start_positions(fence, n, opts.seed)
    own_view = None
    if view is None and opts.view_port is not None:
        from groundstation.liveview import LiveView, ViewError
        try:
            view = own_view = LiveView(opts.view_port).start()
        except ViewError as exc:
            raise DemoError(str(exc)) from None
    if view is not None:
        echo(f"live view: {view.url}")
    try:
        return _run(opts, spec, manifest, flight_cfg, separation, obstacles, fence, anchors, ids, teams, kill, base,
                    starts, view)
    finally:
        if own_view is not None:
            own_view.stop()


def _run(opts, spec, manifest, flight_cfg, separation, obstacles, fence, anchors, ids, teams, kill, base, starts,
         view) -> dict[str, Any]:
    from groundstation.liveview.server import scene
    from groundstation.mcap_log import open_recorder
    n = len(ids)
    the_scene = scene(fence, anchors, spec)
    recorder = open_recorder(opts.log_path, the_scene)  # .mcap: MCAP for Foxglove, else JSON lines
    metrics = EpisodeMetrics(spec, obstacles, separation.capture_distance)
    pairs = PairMonitor(separation.min_distance, 2 * max(spec.per_agent("radius")))
    t_start = time.monotonic()
    result: dict[str, Any] = {}
    sim_cls = SimSwarm if opts.sim_in_process else SimProcess
    with sim_cls(n, base_port=base, seed=opts.seed, start_positions=starts, latency_probe=True) as sims:
        relay = LossyRelay([base + i for i in range(n)], 0.0, opts.seed) if opts.loss > 0 else None
        uris = sims.uris if relay is None else [f"udp://127.0.0.1:{p}" for p in relay.ports]
        links = []
        try:
            links = _open_links(uris, opts.telemetry_period_ms, flight_cfg.link_loss_timeout)
            if relay is not None:
                relay.loss = opts.loss  # only now: cflib's UDP driver does not retransmit TOC requests
            t_connected = time.monotonic()
            by_id = dict(zip(ids, links))
            session = FlightSession(by_id, teams, fence, flight_cfg,
                                    actors=[{"id": a.id, "role": a.role.label} for a in manifest.agents],
                                    record=recorder, latency_probe=True, separation=separation,
                                    separation_process=opts.separation_process)
            if view is not None:
                from groundstation.liveview import SessionSource
                view.attach(SessionSource(session, the_scene, metrics=metrics.live))
            try:
                _fly(opts, spec, session, sims, links, ids, obstacles, metrics, kill, result, pairs, recorder)
            except KeyboardInterrupt:
                _wait_on_ground(sims, 4.0)
                on_ground = sum(1 for tr in sims.truths() if on_ground(tr))
                raise DemoInterrupted({d: s.value for d, s in session.statuses().items()}, on_ground) from None
            # session exit landed everyone it can reach; a drone without a link comes down on its watchdog
            _wait_on_ground(sims, 4.0)
            result.update(results(opts, spec, session, sims, metrics, result.pop("pilot"), ids,
                                   result.pop("sent0"), result.pop("sent1"), result.pop("t_mission"),
                                   result.pop("t_end"), t_start, t_connected, kill, result.pop("kill_link_at", None),
                                   relay))
            result["obstacles"] = [[round(float(v), 3) for v in o] for o in obstacles]
            result.update(separation_results(session, sims, pairs))
            recorder({"t": round(time.monotonic() - session._t0, 4), "event": "drone_contacts", "drone": None,
                      "detail": f"{result['drone_contacts']} drone contacts in the simulator",
                      "count": result["drone_contacts"], "contacts": result["drone_contact_events"]})
        finally:
            if view is not None:
                view.detach()  # the final state stays on the page, without controls
            close_links(links)
            if relay is not None:
                relay.close()
            recorder.close()
    if opts.json_path:  # atomically: an interrupted or failed write leaves the previous file, never half of one
        write_text_atomic(opts.json_path, json.dumps(json_safe(result), indent=2, sort_keys=True, default=str) + "\n")
    if opts.plot_path:
        plot_flight(opts.plot_path, recorder.rows, fence, anchors, ids, teams, result)
    return result


def _fly(opts, spec, session: FlightSession, sims: "SimSwarm | SimProcess", links, ids, obstacles, metrics, kill, result,
         pairs: "PairMonitor", record: Callable[[dict], None] | None = None) -> None:
    """Preflight to landing (the session lands everyone on the way out, whatever happens)."""
    manifest_hash = read_manifest(opts.models).spec.hash
    with session:
        session.preflight(spec_hash=spec.hash, models_spec_hash=manifest_hash)
        _, pols = load_models(opts.models, spec=spec, engine=opts.engine)
        policies = {p.agent_id: p for p in pols}
        session.assign_roles()
        # built on the ground: numba compiles the encoders and every actor runs once before any drone flies
        pilot = AgentPilot(session, spec, policies, obstacles, on_step=metrics)
        session.takeoff()
        t_ready = time.monotonic()
        with pilot:
            # the mission clock starts when every runtime flies its actor (a cold start only delays it)
            t_mission = pilot.begin_mission()
            result["startup_s"] = round(t_mission - t_ready, 3)
            sent0 = [link.stats() for link in links]
            killed = False
            next_metrics = time.monotonic() + METRICS_PERIOD
            while time.monotonic() - t_mission < opts.duration:
                if record is not None and time.monotonic() >= next_metrics:  # the metrics so far, in the log
                    next_metrics += METRICS_PERIOD
                    record({"t": round(session.time(), 4), "event": "metrics", "drone": None, "detail": "",
                            **metrics.live()})
                if kill is not None and not killed and time.monotonic() - t_mission >= kill[1]:
                    sims.kill_link(ids.index(kill[0]))
                    killed = True
                    result["kill_link_at"] = time.monotonic()
                if not session.flying():
                    break
                pairs.update(sims.truths())
                time.sleep(PAIR_PERIOD_S)
        t_end = time.monotonic()
        sent1 = [link.stats() for link in links]
        session.stop_mission()
    result.update(pilot=pilot, sent0=sent0, sent1=sent1, t_mission=t_mission, t_end=t_end)


def _wait_on_ground(sims: "SimSwarm | SimProcess", timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all(not tr.motors_on for tr in sims.truths()):
            return
        time.sleep(0.05)
