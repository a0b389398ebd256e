"""The live view: a web page that shows the swarm while it flies, with land and emergency-stop buttons.

``LiveView`` serves ``static/`` (no build step, nothing from the internet) and the state of one *source* on
its own thread with its own asyncio loop (aiohttp)::

    view = LiveView(port=8765).start()     # binds now: a taken port is a ViewError before anything flies
    view.attach(SessionSource(session, scene(fence, anchors, spec), metrics=metrics.live))
    ...                                    # fly
    view.stop()

The source's ``state()`` is called on the view's thread, ``rate`` times a second, and the same JSON is pushed
over the WebSocket ``/ws`` to every open tab (a slow tab skips frames; it never holds up the others) and
answered to ``GET /api/state``. ``SessionSource.state`` copies what it shows with ``FlightSession.snapshot``,
which takes no drone's lock: the control path never waits on the view.

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

import asyncio
import errno
import json
import logging
import math
import socket
import threading
import time
from pathlib import Path
from typing import Any, Callable, Protocol

from runtime.cliutil import json_safe

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
"""The port of ``--view`` given without one."""
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
    """The live-view server (see the module docstring). ``port=0`` picks a free port (tests)."""

    def __init__(self, port: int = DEFAULT_PORT, host: str = "127.0.0.1", rate: float = 20.0,
                 option: str = "--view") -> None:
        if not rate > 0:
            raise ValueError(f"rate: must be > 0 Hz, got {rate!r}")
        self.host, self.port, self.rate, self.option = host, port, rate, option
        self.source: Source = _Waiting()
        self.frames = 0
        """State messages computed (each pushed to every open WebSocket)."""
        self._latest: str = json.dumps(self.source.state())
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stopped: asyncio.Event | None = None
        self._boxes: dict = {}
        """Open WebSocket -> [latest text, asyncio.Event]: one mailbox per tab."""
        self._sock: socket.socket | None = None

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    @property
    def clients(self) -> int:
        """Open WebSockets (browser tabs)."""
        return len(self._boxes)

    def attach(self, source: Source) -> None:
        """Show ``source`` from now on (the view starts with a "waiting" page)."""
        self.source = source

    def detach(self) -> None:
        """Keep showing the source's last state, with no controls (the flight is over)."""
        try:
            last = self.source.state()
        except Exception:  # a source that cannot answer any more: the last state pushed
            log.exception("live view: the state source failed")
            last = self._last_state()
        if last is not None:
            last["controls"] = []
            last["mission"] = False
            frozen = dict(last)

            class _Frozen(_Waiting):
                def state(self) -> dict[str, Any]:
                    return frozen
            self.source = _Frozen()

    # -- life cycle -------------------------------------------------------------------------------

    def start(self) -> "LiveView":
        """Bind (``ViewError`` if the port is taken), then serve on a thread of its own."""
        self._sock = bind(self.host, self.port, self.option)
        self.port = self._sock.getsockname()[1]
        self._thread = threading.Thread(target=self._run, name="LiveView", daemon=True)
        self._thread.start()
        self._ready.wait(10.0)
        if self._error is not None:
            raise ViewError(f"{self.option}: the live view did not start: {self._error}")
        log.info("live view at %s", self.url)
        return self

    def stop(self) -> None:
        loop, stopped = self._loop, self._stopped
        if loop is not None and stopped is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(stopped.set)
            except RuntimeError:  # the loop closed meanwhile
                pass
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self._sock is not None:
            self._sock.close()

    def __enter__(self) -> "LiveView":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- the view's thread ------------------------------------------------------------------------

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._serve())
        except BaseException as exc:  # reported to start(); after that logged: the flight goes on without a view
            self._error = exc
            log.exception("live view stopped")
        finally:
            self._ready.set()
            try:  # the controls' worker threads (run_in_executor) end with the loop
                loop.run_until_complete(loop.shutdown_default_executor())
            finally:
                loop.close()

    async def _serve(self) -> None:
        from aiohttp import web

        self._stopped = asyncio.Event()
        app = web.Application()
        app.router.add_get("/", self._index)
        app.router.add_get("/api/state", self._get_state)
        app.router.add_get("/ws", self._ws)
        app.router.add_post("/api/land_all", self._post("land_all"))
        app.router.add_post("/api/land/{drone}", self._post("land"))
        app.router.add_post("/api/emergency_stop", self._post("emergency_stop"))
        app.router.add_post("/api/replay", self._post("replay"))
        app.router.add_static("/static/", STATIC, show_index=False)
        runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)
        await runner.setup()
        site = web.SockSite(runner, self._sock)
        await site.start()
        pusher = asyncio.ensure_future(self._push())
        self._ready.set()
        try:
            await self._stopped.wait()
        finally:
            pusher.cancel()
            for ws in list(self._boxes):
                await ws.close()
            await runner.cleanup()

    def _last_state(self) -> dict[str, Any] | None:
        try:
            return json.loads(self._latest)
        except ValueError:
            return None

    def _compute(self) -> str:
        try:
            state = self.source.state()
        except Exception:  # a failing source must not stop the view (nor the flight): keep the last state
            log.exception("live view: the state source failed")
            return self._latest
        state.setdefault("wall_time", time.time())
        try:
            text = json.dumps(state, separators=(",", ":"), allow_nan=False)
        except ValueError:  # NaN or inf somewhere: strict JSON has neither
            text = json.dumps(json_safe(state), separators=(",", ":"), default=str)
        self.frames += 1
        self._latest = text
        return text

    async def _push(self) -> None:
        period = 1.0 / self.rate
        next_t = time.monotonic()
        while True:
            text = self._compute()
            for box in list(self._boxes.values()):
                box[0] = text
                box[1].set()
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t, delay = time.monotonic(), 0.0
            await asyncio.sleep(delay)

    # -- handlers ---------------------------------------------------------------------------------

    async def _index(self, request):
        from aiohttp import web
        return web.FileResponse(STATIC / "index.html")

    async def _get_state(self, request):
        from aiohttp import web
        return web.Response(text=self._latest, content_type="application/json")

    async def _ws(self, request):
        from aiohttp import WSMsgType, web
        ws = web.WebSocketResponse(heartbeat=10.0)
        await ws.prepare(request)
        box: list = [self._latest, asyncio.Event()]
        box[1].set()
        self._boxes[ws] = box

        async def sender() -> None:
            # the latest state only: a slow tab skips frames and never delays another tab
            while not ws.closed:
                await box[1].wait()
                box[1].clear()
                await ws.send_str(box[0])

        task = asyncio.ensure_future(sender())
        try:
            async for msg in ws:  # the page sends nothing the view acts on (controls are POSTs)
                if msg.type == WSMsgType.ERROR:
                    break
        finally:
            task.cancel()
            self._boxes.pop(ws, None)
        return ws

    def _post(self, name: str):
        from aiohttp import web

        async def handler(request):
            args: dict[str, Any] = {}
            if request.can_read_body:
                try:
                    body = await request.json()
                except ValueError:
                    return web.json_response({"ok": False, "error": "the body is not JSON"}, status=400)
                if not isinstance(body, dict):
                    return web.json_response({"ok": False, "error": "the body must be a JSON object"}, status=400)
                args.update(body)
            if "drone" in request.match_info:
                args["drone"] = request.match_info["drone"]
            source = self.source
            if name not in source.controls:
                why = "no flight yet" if isinstance(source, _Waiting) and not source.controls else \
                    f"this view's controls are {', '.join(source.controls) or 'none (the flight is over)'}"
                return web.json_response({"ok": False, "error": f"{name}: {why}"}, status=409)
            loop = asyncio.get_running_loop()
            try:  # the session's methods send to the links: off the view's loop
                out = await loop.run_in_executor(None, source.control, name, args)
            except ControlRefused as exc:
                return web.json_response({"ok": False, "error": str(exc)}, status=400)
            log.warning("live view: %s %s", name, args.get("drone", ""))
            return web.json_response(json_safe(out))

        return handler
