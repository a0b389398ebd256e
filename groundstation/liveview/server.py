"""The live view: a web page that shows the swarm while it flies, with land and emergency-stop buttons.

``LiveView`` serves ``static/`` (no build step, nothing from the internet) and the state of one *source*. The
web server (aiohttp, the JSON encoding, every tab) runs in a process of its own (``webserver``); the ground
station keeps one thread that builds the state and one that runs the page's controls::

    view = LiveView(port=8765).start()     # binds now: a taken port is a ViewError before anything flies
    view.attach(SessionSource(session, scene(fence, anchors, spec), metrics=metrics.live))
    ...                                    # fly
    view.stop()

The source's ``state()`` is called on the view's thread, ``rate`` times a second, and handed to the server's
process, which encodes it once and pushes it over the WebSocket ``/ws`` to every open tab (a slow tab skips
frames; it never holds up the others) and answers it to ``GET /api/state``. ``SessionSource.state`` copies what
it shows with ``FlightSession.snapshot``, which takes no drone's lock: the control path never waits on the view,
and the number of tabs costs the ground station's interpreter nothing.

State (``GET /api/state``; every WebSocket message is one such object)::

    {"mode": "live" | "replay" | "waiting", "t": s, "mission": bool, "controls": ["land_all", ...],
     "drones": [{"id", "team", "role", "actor", "status", "reason", "position": [x, y, z] m, "velocity",
                 "battery": V, "link_quality": 0..1, "position_variance": m^2, "setpoint", "setpoint_age": s,
                 "command_age": s, "telemetry_age": s}, ...],
     "scene": {"arena": {"half_width"}, "fence": {"polygon", "safe_polygon", "margin", "z_band"},
               "keep_out": [{"x", "y", "radius"}], "anchors": [{"id", "position"}], "sensing_range": m},
     "events": [{"i", "t", "drone", "kind", "detail"}, ...],   # the latest ones, "i" counts from 0
     "metrics": {"mean_min_dist", "mean_avg_dist", "mean_max_dist", "tracking_rate", "coverage", ...}}

Controls (POST, JSON body optional; each calls the ``FlightSession``'s own method, never around it):
``/api/land_all`` (``land_all``), ``/api/land/{drone}`` (``land``), ``/api/emergency_stop`` with
``{"confirm": true}`` (``emergency_stop``: every motor off; refused with 400 without the confirmation), and for
a replay ``/api/replay`` with ``{"pause": bool, "seek": s, "speed": x}``.
"""
from __future__ import annotations

import errno
import logging
import socket
import threading
import time
from pathlib import Path
from typing import Any, Callable, Protocol

from runtime.cliutil import json_safe

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
"""The port of ``--view`` given without one."""
START_TIMEOUT_S = 60.0
"""How long the web server's process may take to import and bind [s] (seconds on a cold, busy machine)."""
STATIC = Path(__file__).parent / "static"


class ViewError(RuntimeError):
    """The live view cannot start; the message names the option and the fix."""


class Source(Protocol):
    """What a ``LiveView`` shows: ``state()`` (JSON-ready dict) and the controls it accepts."""

    controls: tuple[str, ...]

    def state(self) -> dict[str, Any]: ...

    def control(self, name: str, args: dict[str, Any]) -> dict[str, Any]: ...


class ControlRefused(ValueError):
    """A control request that is refused (HTTP 400); the message says why."""


# ---- the static scene ----------------------------------------------------------------------------

def scene(fence, anchors=None, spec=None) -> dict[str, Any]:
    """The parts of the picture that do not move: arena, fence and its margin, keep-out circles, anchors."""
    r = lambda v: [round(float(c), 4) for c in v]  # noqa: E731
    out: dict[str, Any] = {
        "fence": {"polygon": [r(p) for p in fence.polygon], "safe_polygon": [r(p) for p in fence.safe_polygon],
                  "margin": fence.margin, "z_band": [fence.z_min, fence.z_max]},
        "keep_out": [{"x": k.x, "y": k.y, "radius": k.radius} for k in fence.keep_out],
        "anchors": [] if anchors is None else [{"id": a.id, "position": r(a.position)} for a in anchors.anchors],
    }
    if spec is not None:
        out["arena"] = {"half_width": spec.arena.half_width}
        out["sensing_range"] = spec.sensing.sensing_range
        out["comm_range"] = spec.sensing.comm_range
    else:
        lo, hi = fence.bounds()
        out["arena"] = {"half_width": float(max(abs(lo[0]), abs(lo[1]), abs(hi[0]), abs(hi[1])))}
        out["sensing_range"] = None
    return out


class SessionSource:
    """A ``FlightSession`` as a live-view source: its snapshot, the static ``scene``, live ``metrics``
    (a callable returning a dict, e.g. the demo's ``EpisodeMetrics.live``), and its controls."""

    controls = ("land_all", "land", "emergency_stop")

    def __init__(self, session, scene: dict[str, Any], metrics: Callable[[], dict] | None = None,
                 extra: Callable[[], dict] | None = None) -> None:
        self.session = session
        self.scene = scene
        self.metrics = metrics
        self.extra = extra

    def state(self) -> dict[str, Any]:
        s = self.session.snapshot()
        s.update(mode="live", scene=self.scene, controls=list(self.controls))
        if self.metrics is not None:
            s["metrics"] = self.metrics()
        if self.extra is not None:
            s.update(self.extra())
        return s

    def control(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        session = self.session
        if name == "land_all":
            session.land_all("live view: land all", wait=False)
        elif name == "land":
            drone = args.get("drone")
            if drone not in session.drones:
                raise ControlRefused(f"drone: {drone!r} is not in this flight ({', '.join(session.drones)})")
            session.land(drone, "live view: land")
        elif name == "emergency_stop":
            if args.get("confirm") is not True:
                raise ControlRefused('emergency_stop: cuts every motor (the drones fall): send {"confirm": true} '
                                     'to confirm')
            session.emergency_stop("live view: emergency stop")
        else:
            raise ControlRefused(f"{name}: not a control of a live flight ({', '.join(self.controls)})")
        return {"ok": True, "control": name, "statuses": {d: s.value for d, s in session.statuses().items()}}


# ---- the server ----------------------------------------------------------------------------------

def bind(host: str, port: int, option: str = "--view") -> socket.socket:
    """A listening TCP socket on ``host:port``; a taken or forbidden port is a ``ViewError`` naming ``option``."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # TIME_WAIT of a previous run, not a live one
        sock.bind((host, port))
        sock.listen(64)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise ViewError(f"{option} {port}: port {port} on {host} is taken (another swarm-gs or another "
                            f"server): give a free one, e.g. {option} {port + 1 if port < 65535 else 8765}") from None
        raise ViewError(f"{option} {port}: cannot listen on {host}:{port}: {exc.strerror or exc}: give another "
                        f"port, e.g. {option} {DEFAULT_PORT}") from None
    sock.setblocking(False)
    return sock


class _Waiting:
    controls: tuple[str, ...] = ()

    def state(self) -> dict[str, Any]:
        return {"mode": "waiting", "t": 0.0, "drones": [], "events": [], "controls": [], "scene": None}

    def control(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        raise ControlRefused(f"{name}: no flight yet (connecting to the drones)")


class LiveView:
    """The live-view server (see the module docstring). ``port=0`` picks a free port (tests).

    In the ground station's interpreter it costs one thread that builds the source's state ``rate`` times a
    second and hands it to the web server's process over a pipe (a pickle, no JSON), and one that runs the
    page's controls; the web server (``webserver``: aiohttp, the encoding, every tab) is a process of its own.
    Measured before the move (the server on a thread of the ground station): one tab cost the interpreter about
    4 % of a core, and every further tab more."""

    def __init__(self, port: int = DEFAULT_PORT, host: str = "127.0.0.1", rate: float = 20.0,
                 option: str = "--view") -> None:
        if not rate > 0:
            raise ValueError(f"rate: must be > 0 Hz, got {rate!r}")
        self.host, self.port, self.rate, self.option = host, port, rate, option
        self.source: Source = _Waiting()
        self.frames = 0
        """States handed to the web server (each pushed to every open WebSocket)."""
        self._last: dict[str, Any] | None = None
        self._clients = 0
        self._proc = None
        self._conn = None
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    @property
    def clients(self) -> int:
        """Open WebSockets (browser tabs)."""
        return self._clients

    def attach(self, source: Source) -> None:
        """Show ``source`` from now on (the view starts with a "waiting" page)."""
        self.source = source

    def detach(self) -> None:
        """Keep showing the source's last state, with no controls (the flight is over)."""
        try:
            last = self.source.state()
        except Exception:  # a source that cannot answer any more: the last state pushed
            log.exception("live view: the state source failed")
            last = self._last
        if last is not None:
            last = dict(last)
            last["controls"] = []
            last["mission"] = False
            frozen = last

            class _Frozen(_Waiting):
                def state(self) -> dict[str, Any]:
                    return frozen
            self.source = _Frozen()

    # -- life cycle -------------------------------------------------------------------------------

    def start(self) -> "LiveView":
        """Start the web server's process; it binds ``host:port`` first (``ViewError`` if the port is taken)."""
        import multiprocessing as mp

        from groundstation.liveview import webserver
        ctx = mp.get_context("spawn")  # no fork of the ground station's threads
        conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=webserver.serve, name="swarm-liveview", daemon=True,
                                 args=(child, self.host, self.port, self.option, str(STATIC), _Waiting().state()))
        self._proc.start()
        child.close()
        self._conn = conn
        try:
            if not conn.poll(START_TIMEOUT_S):
                raise ViewError(f"{self.option}: the live view's server did not start in {START_TIMEOUT_S:.0f} s")
            kind, payload = conn.recv()
        except (EOFError, OSError):
            kind, payload = "error", f"{self.option}: the live view's server exited at start-up " \
                                     f"(exit code {self._proc.exitcode})"
        except ViewError as exc:
            kind, payload = "error", str(exc)
        if kind != "ready":
            self._end_process()
            raise ViewError(payload)
        self.port = int(payload)
        self._stop.clear()
        self._threads = [threading.Thread(target=self._feed, name="LiveView", daemon=True),
                         threading.Thread(target=self._serve_controls, name="LiveViewControls", daemon=True)]
        for t in self._threads:
            t.start()
        log.info("live view at %s", self.url)
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._conn is not None:
            self._send(("stop", None))
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=5.0)
        self._threads = []
        self._end_process()

    def _end_process(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            proc.join(timeout=5.0)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=2.0)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=2.0)
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> "LiveView":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- the ground station's side ----------------------------------------------------------------

    def _send(self, msg: tuple) -> bool:
        try:
            with self._send_lock:
                self._conn.send(msg)
            return True
        except (OSError, ValueError, AttributeError):  # the server is gone (or stopping)
            return False

    def _state(self) -> dict[str, Any] | None:
        try:
            state = self.source.state()
        except Exception:  # a failing source must not stop the view (nor the flight): keep the last state
            log.exception("live view: the state source failed")
            return None
        state.setdefault("wall_time", time.time())
        return state

    def _feed(self) -> None:
        """The source's state to the web server, ``rate`` times a second."""
        period = 1.0 / self.rate
        next_t = time.monotonic()
        while not self._stop.is_set():
            state = self._state()
            if state is not None:
                if not self._send(("state", state)):
                    return
                self._last = state
                self.frames += 1
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t, delay = time.monotonic(), 0.0
            self._stop.wait(delay)

    def _serve_controls(self) -> None:
        """Run the page's controls (POSTs) through the source, one at a time, and answer them."""
        conn = self._conn
        while not self._stop.is_set():
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                return  # the server is gone
            if msg[0] == "clients":
                self._clients = int(msg[1])
            elif msg[0] == "control":
                _, key, name, args = msg
                status, body = self._control(name, args)
                self._send(("reply", key, status, body))

    def _control(self, name: str, args: dict[str, Any]) -> tuple[int, dict[str, Any]]:
        source = self.source
        if name not in source.controls:
            why = "no flight yet" if isinstance(source, _Waiting) and not source.controls else \
                f"this view's controls are {', '.join(source.controls) or 'none (the flight is over)'}"
            return 409, {"ok": False, "error": f"{name}: {why}"}
        try:
            out = source.control(name, args)
        except ControlRefused as exc:
            return 400, {"ok": False, "error": str(exc)}
        except Exception as exc:  # the page gets the error; the flight goes on
            log.exception("live view: control %s failed", name)
            return 500, {"ok": False, "error": f"{name}: {type(exc).__name__}: {exc}"}
        log.warning("live view: %s %s", name, args.get("drone", ""))
        return 200, json_safe(out)
