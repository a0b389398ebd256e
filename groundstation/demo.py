"""``swarm-gs demo``: the whole stack against 12 simulated Crazyflies.

Twelve simulated Crazyflies (``groundstation.sim.SimSwarm``: CRTP over UDP; in a process of their own,
``groundstation.sim.remote.SimProcess``, unless ``sim_in_process``) are connected through unmodified
cflib (``udp://`` URIs, ``CflibLink``); 10 form the pursuer team (pursuer and scout actors) and 2 fly the
evader actors. The arena's three obstacles are drawn from the spec with the seed (``runtime.world``) and
become keep-out circles of the fence (the simulator has no physical obstacles, so the fence is what keeps
drones out of them). Preflight, role assignment, staggered takeoff, the mission flown by the exported actors
(``mission.AgentPilot``: one ``runtime.agent.Agent`` per actor), landing; then the paper's metrics
(``runtime.metrics``, one episode per ``spec.timing.episode_steps`` control periods), link statistics, a
JSON-lines flight log and a picture.

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
import selectors
import socket
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from groundstation.flight import FlightConfig, FlightSession, close_links
from groundstation.link import LinkError, open_link
from groundstation.mission import AgentPilot
from groundstation.positioning import AnchorLayout
from groundstation.roles import EVADER_TEAM, PURSUER_TEAM
from groundstation.safety import FenceConfig, KeepOut, in_safe_set
from groundstation.separation import SeparationConfig
from groundstation.sim.remote import SimProcess
from groundstation.sim.swarm import SimSwarm, free_base_port
from runtime.cliutil import json_safe, write_text_atomic
from runtime.metrics import MetricsAccumulator
from runtime.paper import FLIGHT_TEAM, PAPER
from runtime.policy import load_models, read_manifest
from runtime.spec import SwarmSpec, load_toml

log = logging.getLogger(__name__)

RESULT_KEYS = ("mean_min_dist", "mean_avg_dist", "mean_max_dist", "tracking_rate", "coverage",
               "collisions_per_episode", "episodes", "landed", "geofence_violations", "setpoint_latency_p99_ms",
               "drone_contacts", "min_pair_distance", "pairs_below_min_distance", "separation")
PAIR_PERIOD_S = 0.02
"""How often the demo samples the simulators' ground truth for the closest pair [s] (one message to the
simulators' process; the simulator itself counts every contact at 10 ms)."""
LANDED_Z = 0.05
"""A simulated drone at or below this height with its motors off has landed [m] (``landed``; ``locked`` counts
those of them whose firmware cut the motors instead: a watchdog after link loss, or an emergency stop)."""


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


class LossyRelay:
    """UDP relay between cflib and the simulators that drops datagrams with probability ``loss``."""

    def __init__(self, targets: list[int], loss: float, seed: int = 0, host: str = "127.0.0.1") -> None:
        self.loss = loss
        self.host = host
        self.targets = targets
        self._rng = random.Random(seed)
        self._sel = selectors.DefaultSelector()
        self._front: list[socket.socket] = []
        self._back: list[socket.socket] = []
        self._client: list[tuple[str, int] | None] = [None] * len(targets)
        self.ports: list[int] = []
        self.dropped = 0
        self.forwarded = 0
        for i, port in enumerate(targets):
            f = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            f.bind((host, 0))
            f.setblocking(False)
            b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            b.connect((host, port))
            b.setblocking(False)
            self._sel.register(f, selectors.EVENT_READ, (i, True))
            self._sel.register(b, selectors.EVENT_READ, (i, False))
            self._front.append(f)
            self._back.append(b)
            self.ports.append(f.getsockname()[1])
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="LossyRelay", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            for key, _ in self._sel.select(0.05):
                i, from_client = key.data
                while True:
                    try:
                        data, addr = key.fileobj.recvfrom(256)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:
                        break
                    if from_client:
                        self._client[i] = addr
                    if self._rng.random() < self.loss:
                        self.dropped += 1
                        continue
                    try:
                        if from_client:
                            self._back[i].send(data)
                        elif self._client[i] is not None:
                            self._front[i].sendto(data, self._client[i])
                        self.forwarded += 1
                    except OSError:
                        pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sel.close()
        for s in self._front + self._back:
            s.close()


class EpisodeMetrics:
    """``runtime.metrics`` over the flight: one episode per ``spec.timing.episode_steps`` control periods (a
    shorter last episode counts too). Agents are the actors in spec order at the measured position of the
    drone flying each; an actor left without a drone stays where its last drone was (and takes no part in
    contacts). A capture is the onset of a pursuer-team agent within ``capture_distance`` of an evader."""

    def __init__(self, spec: SwarmSpec, obstacles: np.ndarray, capture_distance: float | None = None) -> None:
        self.spec = spec
        self.capture_distance = spec.sensing.sensing_range if capture_distance is None else capture_distance
        nt = spec.team.n_team
        self.cross = np.zeros((spec.n_agents, spec.n_agents), dtype=bool)
        self.cross[:nt, nt:] = self.cross[nt:, :nt] = True
        self.acc = MetricsAccumulator(spec, 1)
        self.obstacle_pos = obstacles[None, :, :2]
        self.obstacle_radius = obstacles[None, :, 2]
        self.radius = np.array(spec.per_agent("radius"))
        self.steps = 0
        self.trail: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._lock = threading.Lock()
        self.acc.begin_episodes(np.array([0]), self.obstacle_pos, self.obstacle_radius)

    def __call__(self, t: float, pos: np.ndarray, vel: np.ndarray, present: np.ndarray) -> None:
        with self._lock:
            p = pos[None]
            d = p[:, :, None, :] - p[:, None, :, :]
            dist = np.sqrt((d * d).sum(-1))
            # pursuer-team x evader pairs "touch" (a capture) within capture distance; same-team pairs on contact
            reach = np.where(self.cross, self.capture_distance, self.radius[:, None] + self.radius[None, :])
            contacts = (dist <= reach) & ~np.eye(len(pos), dtype=bool)
            contacts &= present[None, :, None] & present[None, None, :]
            od = np.linalg.norm(pos[:, None, :] - self.obstacle_pos[0][None], axis=-1)
            obst = ((od <= self.obstacle_radius[0][None] + self.radius[:, None]).any(-1) & present)[None]
            self.acc.update(p, contacts[None] if contacts.ndim == 2 else contacts, obst, dist)
            self.steps += 1
            self.trail.append((t, pos.copy(), present.copy()))
            if self.steps % self.spec.timing.episode_steps == 0:
                self.acc.end_episodes(np.array([0]))
                self.acc.begin_episodes(np.array([0]), self.obstacle_pos, self.obstacle_radius)

    def summary(self) -> dict[str, float]:
        with self._lock:
            if self.steps % self.spec.timing.episode_steps:
                self.acc.end_episodes(np.array([0]))
            return self.acc.summary()

    def live(self) -> dict[str, float]:
        """The metrics so far, the running episode included (left open), for the live view: every finished
        episode and the running one weigh the same, as in ``summary``."""
        with self._lock:  # a copy of a few numbers: the control thread's update waits microseconds at most
            acc = self.acc
            sums, steps = acc._sums[0].copy(), float(acc._sums[0, 5])
            coverage = float((acc.visited[0] & acc.free[0]).sum() / acc.free_count[0]) if steps else None
            records = list(acc.records)
            captures = int(acc._captures[0]) + sum(r.captures for r in records)
            n = self.steps
        rows = [(r.min_dist, r.avg_dist, r.max_dist, r.tracking_rate, r.coverage) for r in records]
        if steps:
            m = sums / steps
            rows.append((m[0], m[1], m[2], m[3], coverage))
        out: dict[str, Any] = {"episodes": len(records), "steps": n, "captures": captures}
        if rows:
            avg = np.mean(np.array(rows, dtype=float), axis=0)
            out.update({k: round(float(v), 4) for k, v in zip(("mean_min_dist", "mean_avg_dist", "mean_max_dist",
                                                               "tracking_rate", "coverage"), avg)})
            if steps:
                out["coverage_instant"] = round(float(sums[4] / steps), 4)
        return out


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
    cache = tempfile.mkdtemp(prefix="swarm-gs-toc-")
    with concurrent.futures.ThreadPoolExecutor(len(uris)) as ex:
        futures = [ex.submit(open_link, u, period_ms=period_ms, rw_cache=cache, link_loss_timeout=link_loss_timeout)
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
    fence = dataclasses.replace(FenceConfig.from_toml(opts.fence),
                                keep_out=tuple(KeepOut(float(x), float(y), float(r)) for x, y, r in obstacles))
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
                                    record=recorder, latency_probe=True, separation=separation)
            if view is not None:
                from groundstation.liveview import SessionSource
                view.attach(SessionSource(session, the_scene, metrics=metrics.live))
            try:
                _fly(opts, spec, session, sims, links, ids, obstacles, metrics, kill, result, pairs, recorder)
            except KeyboardInterrupt:
                _wait_on_ground(sims, 4.0)
                on_ground = sum(1 for tr in sims.truths() if _on_ground(tr))
                raise DemoInterrupted({d: s.value for d, s in session.statuses().items()}, on_ground) from None
            # session exit landed everyone it can reach; a drone without a link comes down on its watchdog
            _wait_on_ground(sims, 4.0)
            result.update(_results(opts, spec, session, sims, metrics, result.pop("pilot"), ids,
                                   result.pop("sent0"), result.pop("sent1"), result.pop("t_mission"),
                                   result.pop("t_end"), t_start, t_connected, kill, result.pop("kill_link_at", None),
                                   relay))
            result["obstacles"] = [[round(float(v), 3) for v in o] for o in obstacles]
            result.update(_separation_results(session, sims, pairs))
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


class PairMonitor:
    """The closest two airborne simulated drones came (ground truth, centre to centre, 3-D) during the mission,
    and how many times a pair came closer than ``min_distance`` or within ``contact`` (onsets)."""

    def __init__(self, min_distance: float, contact: float) -> None:
        self.min_distance, self.contact = min_distance, contact
        self.closest = math.inf
        self.below = 0
        self.touching = 0
        self.samples = 0
        self._below: np.ndarray | None = None
        self._touch: np.ndarray | None = None

    def update(self, truths: list) -> None:
        p = np.array([t.position for t in truths])
        up = np.array([t.motors_on and t.position[2] > LANDED_Z for t in truths])
        d = np.linalg.norm(p[:, None] - p[None], axis=-1)
        pair = up[:, None] & up[None] & ~np.eye(len(p), dtype=bool)
        below, touch = (d < self.min_distance) & pair, (d <= self.contact) & pair
        if self._below is None:
            self._below, self._touch = np.zeros_like(below), np.zeros_like(touch)
        self.below += int((below & ~self._below).sum()) // 2
        self.touching += int((touch & ~self._touch).sum()) // 2
        self._below, self._touch = below, touch
        if pair.any():
            self.closest = min(self.closest, float(d[pair].min()))
        self.samples += 1


def _separation_results(session: FlightSession, sims: "SimSwarm | SimProcess", pairs: PairMonitor) -> dict:
    return {
        "separation": session.separation_stats(),
        "drone_contacts": sims.drone_contacts,  # two drones that touched: both crashed (motors off, locked)
        "drone_contact_events": [[round(float(t), 3), a, b] for t, a, b in sims.contact_events],
        "min_pair_distance": round(pairs.closest, 4) if math.isfinite(pairs.closest) else None,
        "pairs_below_min_distance": pairs.below,
        "pairs_touching": pairs.touching,
        "min_distance": session.separation_config.min_distance,
        "capture_distance": session.separation_config.capture_distance,
    }


def _on_ground(truth) -> bool:
    return truth.position[2] <= LANDED_Z and not truth.motors_on


def _wait_on_ground(sims: "SimSwarm | SimProcess", timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all(not tr.motors_on for tr in sims.truths()):
            return
        time.sleep(0.05)


def _results(opts, spec, session: FlightSession, sims: "SimSwarm | SimProcess", metrics: EpisodeMetrics, pilot: AgentPilot,
             ids, sent0, sent1, t_mission, t_end, t_start, t_connected, kill, kill_at, relay) -> dict[str, Any]:
    truth = sims.truths()
    landed = sum(1 for tr in truth if _on_ground(tr))
    lat = np.array(session.latencies) * 1e3
    e2e = np.array(sims.latency_samples()) * 1e3
    span = max(t_end - t_mission, 1e-9)
    per_link = {}
    for d, a, b in zip(ids, sent0, sent1):
        per_link[d] = {"packets_sent_per_s": round((b.packets_sent - a.packets_sent) / span, 1),
                       "packets_received_per_s": round((b.packets_received - a.packets_received) / span, 1),
                       "telemetry_per_s": round((b.telemetry_received - a.telemetry_received) / span, 1),
                       "link_lost": b.link_lost}
    sent = np.array([v["packets_sent_per_s"] for v in per_link.values()])
    recv = np.array([v["packets_received_per_s"] for v in per_link.values()])
    summary = metrics.summary()
    events = [{"t": round(e.t - t_mission, 3), "drone": e.drone, "kind": e.kind, "detail": e.detail}
              for e in session.events if e.kind not in ("status",)]
    res: dict[str, Any] = {k: summary.get(k) for k in ("mean_min_dist", "mean_avg_dist", "mean_max_dist",
                                                       "tracking_rate", "coverage", "coverage_instant",
                                                       "collisions_per_episode", "captures_per_episode")}
    t = spec.team
    if (t.n_pursuers, t.n_scouts, t.n_evaders) == FLIGHT_TEAM:  # the paper's real-drone team: its figure beside
        res["paper_flight_mean_avg_dist"] = PAPER["paper_flight"]["mean_avg_dist"]
    res.update({
        "episodes": summary.get("episodes", 0),
        "landed": landed,
        "locked": sum(1 for tr in truth if tr.supervisor == "locked"),
        "drones": len(ids),
        "geofence_violations": session.geofence_violations(),
        "ground_station_stalls": session.stalls,
        "setpoint_latency_p99_ms": float(np.percentile(e2e, 99)) if e2e.size else None,
        "setpoint_latency_p50_ms": float(np.percentile(e2e, 50)) if e2e.size else None,
        "setpoint_latency_samples": int(e2e.size),
        "ground_station_latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
        "ground_station_latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
        "setpoints": int(lat.size),
        "mission_s": round(span, 2),
        "connect_s": round(t_connected - t_start, 2),
        "wall_s": round(time.monotonic() - t_start, 2),
        "control_periods": pilot.ticks,
        "agents": pilot.stats(),
        "final_status": {d: s.value for d, s in session.statuses().items()},
        "final_truth": {d: {"z": round(tr.position[2], 3), "motors_on": tr.motors_on, "supervisor": tr.supervisor}
                        for d, tr in zip(ids, truth)},
        "final_roles": session.assignment.by_drone,
        "role_changes": [c.describe() for c in session.role_changes],
        "events": events,
        "links": {"per_drone": per_link,
                  "mean_packets_sent_per_s": float(sent.mean()), "mean_packets_received_per_s": float(recv.mean()),
                  "total_packets_per_s": float(sent.sum() + recv.sum()),
                  "telemetry_period_ms": opts.telemetry_period_ms, "loss": opts.loss,
                  "relay_dropped": relay.dropped if relay else 0},
        "spec_hash": spec.hash,
        "models": str(opts.models), "engine": opts.engine,
        "seed": opts.seed,
        "speed": opts.speed,
        "duration": opts.duration,
        "simulator": "in-process" if opts.sim_in_process else "own process",
    })
    if kill is not None:
        lost = [e for e in session.events if e.kind == "link_lost" and e.drone == kill[0]]
        cut = kill_at
        res["kill_link"] = {"drone": kill[0], "at_s": kill[1], "cut": cut is not None,
                            "detected_after_ms": round((lost[0].t - cut) * 1e3, 1) if lost and cut else None}
    return res


def plot_flight(path: str, rows: list[dict], fence: FenceConfig, anchors: AnchorLayout, ids: list[str],
                teams: dict[str, str], result: dict[str, Any]) -> None:
    """Top-down trajectories from the flight log on the arena, fence, keep-outs and anchors."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from groundstation.positioning import draw_layout

    colors = {"pursuer": "tab:red", "scout": "tab:blue", "evader": "tab:green", None: "tab:gray"}  # as training.plots
    fig, ax = plt.subplots(figsize=(7, 7))
    draw_layout(ax, fence, anchors)
    for d in ids:
        pts = [(r["position"], r.get("role"), r["state"]) for r in rows
               if r.get("drone") == d and "event" not in r and r.get("position") is not None
               and r["state"] in ("flying", "holding", "landing", "lost", "taking_off")]
        if not pts:
            continue
        xy = np.array([p[0][:2] for p in pts])
        role = next((p[1] for p in reversed(pts) if p[1]), None)
        ax.plot(xy[:, 0], xy[:, 1], "-", color=colors.get(role, "tab:gray"), linewidth=0.9, alpha=0.8)
        ax.plot(xy[0, 0], xy[0, 1], "o", color=colors.get(role, "tab:gray"), markersize=4)
        end = pts[-1][2]
        ax.plot(xy[-1, 0], xy[-1, 1], "x" if end == "lost" else "s", color=colors.get(role, "tab:gray"),
                markersize=6 if end == "lost" else 4)
        ax.annotate(d, xy[-1], fontsize=6, xytext=(3, 3), textcoords="offset points")
    for role, c in colors.items():
        if role:
            ax.plot([], [], "-", color=c, label=role)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"swarm-gs demo: {result.get('drones')} drones, {result.get('mission_s')} s, "
                 f"landed {result.get('landed')}, fence violations {result.get('geofence_violations')}", fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    lo, hi = fence.bounds()
    ax.set_xlim(lo[0] - 0.5, hi[0] + 0.5)
    ax.set_ylim(lo[1] - 0.5, hi[1] + 0.5)
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=120, bbox_inches="tight")
    plt.close(fig)


def format_summary(res: dict[str, Any]) -> str:
    """The printed report of a demo run."""
    f = lambda v, d=3: "-" if v is None else (f"{v:.{d}f}" if isinstance(v, float) else str(v))  # noqa: E731
    links = res["links"]
    ag = res["agents"]
    sep = res["separation"]
    lines = [
        f"mission {res['mission_s']} s, {res['episodes']} episode(s), {res['control_periods']} control periods; "
        f"agents: {ag['actions']} actions, {ag['deadline_misses']} deadline misses, {ag['faults']} faults, tick to "
        f"command p50 {f(ag['tick_to_command_p50_ms'], 2)} ms p99 {f(ag['tick_to_command_p99_ms'], 2)} ms",
        f"distance to targets  min {f(res['mean_min_dist'])}  mean {f(res['mean_avg_dist'])}  "
        f"max {f(res['mean_max_dist'])} m"
        + (f"   (paper's real flight, 2 pursuers + 3 scouts vs 1 evader: mean {res['paper_flight_mean_avg_dist']} m)"
           if "paper_flight_mean_avg_dist" in res else ""),
        f"tracking rate {f(res['tracking_rate'])}   coverage {f(res['coverage'])}   "
        f"collisions/episode {f(res['collisions_per_episode'], 2)}   captures/episode "
        f"{f(res['captures_per_episode'], 2)} (within {f(res['capture_distance'], 2)} m)",
        f"separation {'on' if res['separation']['enabled'] else 'OFF'} (min {f(res['min_distance'], 2)} m): drone "
        f"contacts {f(res['drone_contacts'])}, closest pair {f(res['min_pair_distance'])} m, "
        f"{res['pairs_below_min_distance']} times closer than min, {res['pairs_touching']} touching (truth)"
        + (f"; changed {sep['changed_setpoints']} of {sep['setpoints']} setpoints, braked {sep['braked_setpoints']} "
           f"({sep['unplaced_setpoints']} without a fresh position)" if sep["enabled"] else ""),
        f"landed {res['landed']}/{res['drones']} ({res['locked']} locked)   geofence violations "
        f"{res['geofence_violations']}   ground-station stalls {res['ground_station_stalls']}",
        f"measurement-to-setpoint at the drone (through cflib and UDP) p50 {f(res['setpoint_latency_p50_ms'], 2)} ms "
        f"p99 {f(res['setpoint_latency_p99_ms'], 2)} ms; in the ground station p50 "
        f"{f(res['ground_station_latency_p50_ms'], 2)} ms p99 {f(res['ground_station_latency_p99_ms'], 2)} ms",
        f"links: {f(links['mean_packets_sent_per_s'], 1)} packets/s sent and {f(links['mean_packets_received_per_s'], 1)} "
        f"received per drone; {f(links['total_packets_per_s'], 0)} packets/s in all (telemetry every "
        f"{links['telemetry_period_ms']} ms, loss {links['loss']}, {links['relay_dropped']} dropped)",
    ]
    for e in res["events"]:
        if e["kind"] in ("link_lost", "low_battery", "agent_fault", "position_invalid", "fence_breach",
                         "roles_reassigned", "abort", "emergency_stop", "dropped", "ground_station_stall"):
            lines.append(f"  t={e['t']:+.2f} s {e['drone'] or '':>5} {e['kind']}: {e['detail']}")
    if "kill_link" in res:
        k = res["kill_link"]
        lines.append(f"link of {k['drone']} cut at {k['at_s']} s: detected after {f(k['detected_after_ms'], 0)} ms")
    return "\n".join(lines)
