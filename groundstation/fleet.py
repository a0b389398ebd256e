"""Real drones: the fleet file, and ``swarm-gs fly / land / status`` over it.

``fleet.toml`` (see ``configs/fleet_example.toml``) names every drone by URI and team and points at the
models, the fence and the LPS anchor layout; an optional ``[flight]`` table overrides ``FlightConfig`` and an
optional ``[separation]`` table ``separation.SeparationConfig`` (``load_separation``).
``fly`` is the demo's code path with ``radio://`` links: preflight, role assignment, staggered takeoff, the
mission flown by the exported actors, landing (also on Ctrl-C and on any error). The fence's keep-out
circles are the obstacles the actors observe, so measure the real ones into the fence file.
"""
from __future__ import annotations

import concurrent.futures
import logging
import math
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from groundstation.fence import check_arena
from groundstation.flight import FlightConfig, FlightSession, close_links
from groundstation.link import FlightState, Link, LinkError, open_link
from groundstation.mission import AgentPilot
from groundstation.positioning import AnchorLayout
from groundstation.roles import EVADER_TEAM, PURSUER_TEAM
from groundstation.safety import FenceConfig, check_position
from groundstation.separation import SeparationConfig
from runtime.policy import load_models, read_manifest
from runtime.spec import ENGINES, SpecError, SwarmSpec, from_mapping, load_toml

log = logging.getLogger(__name__)

TOC_CACHE = Path(tempfile.gettempdir()) / "swarm-gs-cflib-toc"
"""Where cflib caches the drones' log and parameter tables of contents (by CRC): reconnects skip the download."""


@dataclass(frozen=True)
class DroneEntry:
    """One drone of the fleet."""

    id: str
    """Name used in logs and role assignment (e.g. "cf1")."""
    uri: str
    """``radio://0/80/2M/E7E7E7E701``, ``udp://127.0.0.1:19850`` or ``mavlink:udpin:...``."""
    team: str
    """"pursuer" (flies pursuer and scout actors) or "evader"; required."""

    def __post_init__(self) -> None:
        if not self.id:
            raise SpecError("id: must not be empty")
        if self.team not in (PURSUER_TEAM, EVADER_TEAM):
            raise SpecError(f"team: {self.team!r} is not 'pursuer' or 'evader'")
        if ":" not in self.uri:
            raise SpecError(f"uri: {self.uri!r} is not a link URI such as radio://0/80/2M/E7E7E7E701")


@dataclass(frozen=True)
class FleetConfig:
    """The ``[fleet]`` table. Relative paths are relative to the fleet file's folder."""

    drones: tuple[DroneEntry, ...] = ()
    """Every drone, as ``[[fleet.drones]]`` tables."""
    models: str = "models/role_based"
    """Models folder written by ``swarm-export onnx`` (manifest.json + one actor per agent)."""
    spec: str = ""
    """TOML whose [spec] table the models were trained on ("" = the default spec)."""
    fence: str = "configs/fence.toml"
    anchors: str = ""
    """LPS anchor layout TOML; when set it is validated against the fence before flying ("" = none)."""
    require_all: bool = True
    """Refuse to fly when any drone fails preflight (else fly without it)."""
    telemetry_period_ms: int = 20
    """Telemetry period per drone [ms]."""
    connect_timeout: float = 10.0
    """[s]"""
    engine: str = "onnxruntime"
    """How the actors run (``runtime.spec.ENGINES``): "onnxruntime", or "compiled" (the same ONNX actors
    compiled with numba, checked against onnxruntime when loaded)."""

    def __post_init__(self) -> None:
        if self.engine not in ENGINES:
            raise SpecError(f"engine: {self.engine!r} is not 'onnxruntime' or 'compiled'")
        ids = [d.id for d in self.drones]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise SpecError(f"drones: ids {dup} appear more than once")
        uris = [d.uri for d in self.drones]
        dup = sorted({u for u in uris if uris.count(u) > 1})
        if dup:
            raise SpecError(f"drones: URIs {dup} appear more than once")
        if not 10 <= self.telemetry_period_ms <= 1000:
            raise SpecError(f"telemetry_period_ms: must be in 10..1000, got {self.telemetry_period_ms}")

    @classmethod
    def from_toml(cls, path: str | Path) -> tuple["FleetConfig", FlightConfig]:
        """The fleet and its flight settings; relative paths resolved against the file's folder."""
        p = Path(path)
        doc = load_toml(p)
        unknown = sorted(set(doc) - set(TABLES))
        if unknown:
            raise SpecError(f"{p}: unknown table [{unknown[0]}]; a fleet file has [fleet], [flight] and [separation]")
        fleet = from_mapping(cls, doc.get("fleet", {}), "fleet")
        if not fleet.drones:
            raise SpecError(f"{p}: fleet.drones: the fleet has no drones: add [[fleet.drones]] tables with id, uri "
                            f"and team")
        flight = FlightConfig.from_dict(doc.get("flight", {}))
        base = p.resolve().parent

        def resolve(v: str) -> str:
            if not v or Path(v).is_absolute() or Path(v).exists():
                return v
            return str(base / v)

        import dataclasses
        fleet = dataclasses.replace(fleet, models=resolve(fleet.models), spec=resolve(fleet.spec),
                                    fence=resolve(fleet.fence), anchors=resolve(fleet.anchors))
        return fleet, flight


TABLES = ("fleet", "flight", "separation")
"""The tables of a fleet file."""


def load_separation(path: str | Path) -> SeparationConfig:
    """The fleet file's ``[separation]`` table (defaults when absent); unknown keys name the field."""
    return SeparationConfig.from_dict(load_toml(path).get("separation", {}))


def open_fleet(fleet: FleetConfig, link_loss_timeout: float = 0.25) -> dict[str, Link]:
    """Connect to every drone in parallel; ``LinkError`` listing every drone that did not answer."""
    def one(d: DroneEntry) -> Link:
        opts: dict[str, Any] = {}
        if not d.uri.startswith("mavlink:"):
            opts = {"period_ms": fleet.telemetry_period_ms, "connect_timeout": fleet.connect_timeout,
                    "link_loss_timeout": link_loss_timeout, "rw_cache": str(TOC_CACHE)}
        return open_link(d.uri, **opts)

    links: dict[str, Link] = {}
    errors: list[str] = []
    with concurrent.futures.ThreadPoolExecutor(len(fleet.drones)) as ex:
        for d, fut in [(d, ex.submit(one, d)) for d in fleet.drones]:
            try:
                links[d.id] = fut.result()
            except LinkError as exc:
                errors.append(f"{d.id}: {exc}")
    if errors:
        close_links(links.values())
        raise LinkError(", ".join(d.uri for d in fleet.drones), "some drones did not answer:\n" + "\n".join(errors),
                        "power them, check the radio and the URIs in the fleet file")
    return links


def obstacles_from_fence(fence: FenceConfig, spec: SwarmSpec) -> np.ndarray:
    """The fence's keep-out circles as the actors' obstacles [K, 3] (x, y, radius) [m]."""
    need = min(spec.sensing.n_obstacles_observed, spec.arena.n_obstacles)
    if len(fence.keep_out) < need:
        raise SpecError(f"fence.keep_out: the actors observe {need} obstacles, the fence lists "
                        f"{len(fence.keep_out)}: add the real obstacles as keep-out circles")
    return np.array([[k.x, k.y, k.radius] for k in fence.keep_out], dtype=float).reshape(-1, 3)


def fly(fleet: FleetConfig, flight: FlightConfig, duration: float, log_path: str | None = None,
        stop: threading.Event | None = None, echo: Callable[[str], None] | None = None,
        separation: SeparationConfig = SeparationConfig(), view_port: int | None = None) -> dict[str, Any]:
    """Fly the fleet's mission for ``duration`` s (or until ``stop`` is set), then land everyone. ``echo`` gets
    the progress lines (the roles, who flies); by default they are logged, and a CLI passes ``print``.
    ``view_port``: serve the live view (``groundstation.liveview``) there during the flight; a taken port is a
    ``ViewError`` before any radio link opens. The view's land and stop buttons call the session's methods."""
    echo = echo or (lambda line: log.info("%s", line))
    spec = SwarmSpec.from_toml(fleet.spec) if fleet.spec else SwarmSpec()
    manifest = read_manifest(fleet.models)
    fence = FenceConfig.from_toml(fleet.fence, spec=manifest.spec)
    check_arena(fence, manifest.spec, f"fleet.fence {fleet.fence}", f"the models in {fleet.models}")
    if fleet.anchors:
        AnchorLayout.from_toml(fleet.anchors, fence=fence)
    obstacles = obstacles_from_fence(fence, spec)
    teams = {d.id: d.team for d in fleet.drones}
    view = None
    if view_port is not None:
        from groundstation.liveview import LiveView
        view = LiveView(view_port).start()
        echo(f"live view: {view.url}")
    try:
        return _fly(fleet, flight, duration, log_path, stop, echo, separation, spec, manifest, fence, obstacles,
                    teams, view)
    finally:
        if view is not None:
            view.stop()


def _fly(fleet, flight, duration, log_path, stop, echo, separation, spec, manifest, fence, obstacles, teams,
         view) -> dict[str, Any]:
    from groundstation.demo_metrics import EpisodeMetrics
    from groundstation.liveview.server import scene
    from groundstation.mcap_log import open_recorder
    anchors = AnchorLayout.from_toml(fleet.anchors, fence=fence) if fleet.anchors else None
    the_scene = scene(fence, anchors, spec)
    recorder = open_recorder(log_path, the_scene, keep=False)  # .mcap: MCAP for Foxglove, else JSON lines
    stop = stop or threading.Event()
    metrics = EpisodeMetrics(spec, obstacles, separation.capture_distance)  # the paper's metrics, live in the view
    links = open_fleet(fleet, flight.link_loss_timeout)
    try:
        session = FlightSession(links, teams, fence, flight,
                                actors=[{"id": a.id, "role": a.role.label} for a in manifest.agents], record=recorder,
                                separation=separation, separation_process=True)
        if view is not None:
            from groundstation.liveview import SessionSource
            view.attach(SessionSource(session, the_scene, metrics=metrics.live))
        with session:
            session.preflight(spec_hash=spec.hash, models_spec_hash=manifest.spec.hash,
                              require_all=fleet.require_all)
            _, pols = load_models(fleet.models, spec=spec, engine=fleet.engine)
            session.assign_roles()
            echo(f"roles: {session.assignment.by_drone}")
            # built on the ground: numba compiles the encoders and every actor runs once before any drone flies
            pilot = AgentPilot(session, spec, {p.agent_id: p for p in pols}, obstacles,
                               on_step=metrics if view is not None else None)  # live metrics for the view
            session.takeoff()
            echo(f"flying: {', '.join(session.flying())}")
            with pilot:
                pilot.begin_mission()  # when every runtime has its first command: a slow start only waits
                end = time.monotonic() + duration
                while time.monotonic() < end and session.flying() and not stop.is_set():
                    stop.wait(0.1)
            session.stop_mission()
        return {"final_status": {d: s.value for d, s in session.statuses().items()},
                "geofence_violations": session.geofence_violations(),
                "separation": session.separation_stats(),
                "events": [(round(e.t - session._t0, 3), e.drone, e.kind, e.detail) for e in session.events
                           if e.kind != "status"]}
    finally:
        if view is not None:
            view.detach()
        close_links(links.values())
        recorder.close()


def land_fleet(fleet: FleetConfig, speed: float = 0.3, timeout: float = 10.0) -> dict[str, str]:
    """Land every drone of the fleet that is flying (e.g. after a ground station crashed)."""
    links = open_fleet(fleet)
    out: dict[str, str] = {}
    try:
        for d, link in links.items():
            tel = link.telemetry()
            if tel is not None and tel.flight_state is FlightState.FLYING:
                link.land(max(tel.position[2], 0.1) / speed + 0.2)
                out[d] = "landing"
            else:
                out[d] = tel.flight_state.value if tel is not None else "no telemetry"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and any(v == "landing" for v in out.values()):
            for d, link in links.items():
                tel = link.telemetry()
                if out[d] == "landing" and tel is not None and tel.flight_state is not FlightState.FLYING:
                    out[d] = f"landed ({tel.flight_state.value})"
            time.sleep(0.05)
        return out
    finally:
        close_links(links.values())


def fleet_status(fleet: FleetConfig) -> list[dict[str, Any]]:
    """One row per drone: state, battery, position, position variance, fence status, link figures."""
    fence = FenceConfig.from_toml(fleet.fence)
    links = open_fleet(fleet)
    try:
        time.sleep(0.3)  # a few samples of the slow log block (battery, variance)
        rows = []
        for d in fleet.drones:
            link = links[d.id]
            tel = link.telemetry()
            st = link.stats()
            rows.append({
                "drone": d.id, "uri": d.uri, "team": d.team,
                "state": tel.flight_state.value if tel else "no telemetry",
                "battery_v": round(tel.battery, 2) if tel and math.isfinite(tel.battery) else None,
                "position": [round(c, 3) for c in tel.position] if tel else None,
                "position_variance": float(f"{max(tel.position_variance):.2g}") if tel and tel.position_variance
                else None,
                "fence": check_position(fence, tel.position).value if tel else None,
                "link_quality": round(tel.link_quality, 2) if tel else None,
                "telemetry_per_s": round(st.telemetry_received / max(time.monotonic() - st.opened_at, 1e-3), 1),
            })
        return rows
    finally:
        close_links(links.values())
