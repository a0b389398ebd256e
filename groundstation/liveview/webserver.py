"""The live view's web server, in a process of its own (``LiveView`` starts it): aiohttp, the page, the
WebSocket pushes and the JSON encoding all run here, not in the ground station's interpreter, so that any
number of browser tabs costs the control path nothing.

It talks to the ``LiveView`` in the ground station over one pipe. From the ground station: ``("state", dict)``
(the latest state, ``rate`` times a second; encoded here once and pushed to every tab), ``("reply", id, status,
body)`` (the answer to a control) and ``("stop", None)``. To it: ``("ready", port)`` or ``("error", message)``
once, then ``("control", id, name, args)`` for every POST, which the ground station runs through the flight
session's own methods, and ``("clients", n)`` when the number of open WebSockets changes. When the ground station
goes away (the pipe closes) the server stops.
"""
from __future__ import annotations

import asyncio
import itertools
import json
import logging
from typing import Any

from runtime.cliutil import json_safe

log = logging.getLogger(__name__)

CONTROL_TIMEOUT_S = 30.0
"""How long a POST waits for the ground station to run its control [s] (then 503)."""


def encode(state: dict[str, Any]) -> str:
    """Strict JSON of a state (NaN and inf spelled as ``json_safe`` does; anything else unknown as text)."""
    try:
        return json.dumps(state, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError):
        return json.dumps(json_safe(state), separators=(",", ":"), default=str)


def serve(conn, host: str, port: int, option: str, static: str, waiting: dict[str, Any]) -> None:
    """The child process's main: bind, report, serve until told to stop or the ground station is gone."""
    logging.basicConfig(level=logging.WARNING)
    from groundstation.liveview.server import ViewError, bind
    try:
        sock = bind(host, port, option)
    except ViewError as exc:
        conn.send(("error", str(exc)))
        conn.close()
        return
    try:
        asyncio.run(_Server(conn, sock, static, encode(waiting)).run())
    finally:
        sock.close()
        conn.close()


class _Server:
    def __init__(self, conn, sock, static: str, latest: str) -> None:
        self.conn, self.sock, self.static = conn, sock, static
        self.latest = latest
        self.boxes: dict = {}
        """Open WebSocket -> [latest text, asyncio.Event]: one mailbox per tab."""
        self.pending: dict[int, asyncio.Future] = {}
        self.ids = itertools.count()
        self.stopped: asyncio.Event | None = None

    async def run(self) -> None:
        from pathlib import Path

        from aiohttp import web

        loop = asyncio.get_running_loop()
        self.stopped = asyncio.Event()
        app = web.Application()
        app.router.add_get("/", self._index)
        app.router.add_get("/api/state", self._get_state)
        app.router.add_get("/ws", self._ws)
        for path, name in (("/api/land_all", "land_all"), ("/api/land/{drone}", "land"),
                           ("/api/emergency_stop", "emergency_stop"), ("/api/replay", "replay")):
            app.router.add_post(path, self._post(name))
        app.router.add_static("/static/", Path(self.static), show_index=False)
        runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)
        await runner.setup()
        await web.SockSite(runner, self.sock).start()
        loop.add_reader(self.conn.fileno(), self._on_pipe)
        self.conn.send(("ready", self.sock.getsockname()[1]))
        try:
            await self.stopped.wait()
        finally:
            loop.remove_reader(self.conn.fileno())
            for fut in self.pending.values():
                fut.cancel()
            for ws in list(self.boxes):
                await ws.close()
            await runner.cleanup()

    # -- the pipe ---------------------------------------------------------------------------------

    def _on_pipe(self) -> None:
        try:
            while self.conn.poll():
                self._handle(self.conn.recv())
        except (EOFError, OSError):  # the ground station is gone: so is its view
            self.stopped.set()

    def _handle(self, msg: tuple) -> None:
        kind = msg[0]
        if kind == "state":
            text = encode(msg[1])
            self.latest = text
            for box in list(self.boxes.values()):
                box[0] = text
                box[1].set()
        elif kind == "reply":
            fut = self.pending.pop(msg[1], None)
            if fut is not None and not fut.done():
                fut.set_result((msg[2], msg[3]))
        elif kind == "stop":
            self.stopped.set()

    def _send(self, msg: tuple) -> None:
        try:
            self.conn.send(msg)
        except (OSError, ValueError):
            self.stopped.set()

    # -- handlers ---------------------------------------------------------------------------------

    async def _index(self, request):
        from pathlib import Path

        from aiohttp import web
        return web.FileResponse(Path(self.static) / "index.html")

    async def _get_state(self, request):
        from aiohttp import web
        return web.Response(text=self.latest, content_type="application/json")

    async def _ws(self, request):
        from aiohttp import WSMsgType, web
        ws = web.WebSocketResponse(heartbeat=10.0)
        await ws.prepare(request)
        box: list = [self.latest, asyncio.Event()]
        box[1].set()
        self.boxes[ws] = box
        self._send(("clients", len(self.boxes)))

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
            self.boxes.pop(ws, None)
            self._send(("clients", len(self.boxes)))
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
            key = next(self.ids)
            fut = asyncio.get_running_loop().create_future()
            self.pending[key] = fut
            self._send(("control", key, name, args))
            try:
                status, out = await asyncio.wait_for(fut, CONTROL_TIMEOUT_S)
            except asyncio.TimeoutError:
                self.pending.pop(key, None)
                return web.json_response({"ok": False, "error": f"{name}: the ground station did not answer in "
                                                                 f"{CONTROL_TIMEOUT_S:.0f} s"}, status=503)
            return web.Response(text=encode(out), status=status, content_type="application/json")

        return handler
