"""Flight logs as MCAP for Foxglove, and the one place that picks a log's format by its suffix.

``open_recorder(path, scene)`` returns the recorder a ``FlightSession`` writes its rows to: ``McapRecorder``
for ``*.mcap``, ``flight_records.JsonlRecorder`` (JSON lines) for anything else. ``read_log(path)`` reads
either back as the same list of rows (``swarm-gs replay`` and ``report`` use it).

The rows are the flight log's (``flight_records.SessionCore._write_rows`` and ``_event``): a *state row* per
drone and record period (``drone``, ``role``, ``actor``, ``state``, ``position``, ``setpoint``, ...) and an *event row*
(``event``, ``drone``, ``detail``, ...). Two event kinds carry no failsafe: ``scene`` (the fence, keep-out
circles and anchors, first row of a log written through ``open_recorder``) and ``metrics`` (the paper's
metrics so far, written by the demo once a second).

MCAP channels (every message JSON-encoded; log time = wall clock of the flight, ns):

=============================  ========================  ==========================================================
topic                          schema                    content
=============================  ========================  ==========================================================
``/scene``                     ``foxglove.SceneUpdate``  the fence (line loop), its margin, keep-out cylinders and
                                                         LPS anchors once (entity ids ``fence``, ``keep_out/K``,
                                                         ``anchor/N``), then every drone each record period
                                                         (entity ``drone/ID``: a sphere coloured by role, pursuers
                                                         red, scouts blue, evaders green, and its id as text)
``/drones/poses``              ``foxglove.PosesInFrame`` every drone's position each record period, frame ``world``
``/log``                       ``foxglove.Log``          every event as a log line (failsafes at WARNING/ERROR)
``/drones/ID/status``          ``swarmpursuit.DroneStatus``  the state row of one drone, as in the JSON-lines log
``/drones/ID/setpoint``        ``swarmpursuit.Setpoint``     its velocity setpoint [m/s] and that setpoint's age [s]
``/events``                    ``swarmpursuit.Event``        every event row, as in the JSON-lines log
``/metrics``                   ``swarmpursuit.Metrics``      the paper's metrics so far (min / mean / max distance,
                                                             tracking, coverage)
``/scene/static``              ``swarmpursuit.Scene``        the scene row (what the live view and replay draw)
=============================  ========================  ==========================================================

Messages go out in chunks of ``chunk_size`` bytes (64 KiB): a flight cut short (Ctrl-C, a killed process)
loses at most the last chunk, and ``read_log`` reads the chunks written before the cut (no summary needed).
"""
from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

from groundstation.flight_records import JsonlRecorder

log = logging.getLogger(__name__)

ROLE_RGBA = {"pursuer": (0.84, 0.15, 0.16, 1.0), "scout": (0.12, 0.47, 0.71, 1.0),
             "evader": (0.17, 0.63, 0.17, 1.0), None: (0.5, 0.5, 0.5, 1.0)}
"""Role colours, as the live view and ``training.plots`` draw them."""
ERROR_EVENTS = ("link_lost", "low_battery", "agent_fault", "fence_breach", "emergency_stop", "dropped", "abort")
WARNING_EVENTS = ("position_invalid", "roles_reassigned", "ground_station_stall", "preflight_failed")
LOG_INFO, LOG_WARNING, LOG_ERROR = 2, 3, 4
"""``foxglove.Log`` levels."""
DRONE_SIZE = 0.15
"""Diameter of a drone's sphere in the scene [m] (a Crazyflie 2.x is about 0.1 m across)."""

# ---- schemas (JSON Schema; Foxglove's well-known ones restricted to the fields written) -----------

_NUM = {"type": "number"}
_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_VEC3 = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM}}
_QUAT = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM}}
_POSE = {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT}}
_COLOR = {"type": "object", "properties": {"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM}}
_PRIM = {"type": "object", "properties": {"pose": _POSE, "size": _VEC3, "color": _COLOR}}
_ARR = lambda items: {"type": "array", "items": items}  # noqa: E731
SCHEMAS: dict[str, dict] = {
    "foxglove.SceneUpdate": {"title": "foxglove.SceneUpdate", "type": "object", "properties": {
        "deletions": _ARR({"type": "object"}),
        "entities": _ARR({"type": "object", "properties": {
            "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"}, "lifetime": _TIME,
            "frame_locked": {"type": "boolean"},
            "metadata": _ARR({"type": "object", "properties": {"key": {"type": "string"},
                                                               "value": {"type": "string"}}}),
            "arrows": _ARR(_PRIM), "cubes": _ARR(_PRIM), "spheres": _ARR(_PRIM),
            "cylinders": _ARR({"type": "object", "properties": {"pose": _POSE, "size": _VEC3, "bottom_scale": _NUM,
                                                                "top_scale": _NUM, "color": _COLOR}}),
            "lines": _ARR({"type": "object", "properties": {
                "type": {"type": "integer"}, "pose": _POSE, "thickness": _NUM, "scale_invariant": {"type": "boolean"},
                "points": _ARR(_VEC3), "color": _COLOR, "colors": _ARR(_COLOR), "indices": _ARR({"type": "integer"})}}),
            "triangles": _ARR({"type": "object"}),
            "texts": _ARR({"type": "object", "properties": {
                "pose": _POSE, "billboard": {"type": "boolean"}, "font_size": _NUM,
                "scale_invariant": {"type": "boolean"}, "color": _COLOR, "text": {"type": "string"}}}),
            "models": _ARR({"type": "object"})}})}},
    "foxglove.PosesInFrame": {"title": "foxglove.PosesInFrame", "type": "object", "properties": {
        "timestamp": _TIME, "frame_id": {"type": "string"}, "poses": _ARR(_POSE)}},
    "foxglove.Log": {"title": "foxglove.Log", "type": "object", "properties": {
        "timestamp": _TIME, "level": {"type": "integer"}, "message": {"type": "string"}, "name": {"type": "string"},
        "file": {"type": "string"}, "line": {"type": "integer"}}},
    "swarmpursuit.DroneStatus": {"title": "swarmpursuit.DroneStatus", "type": "object", "properties": {
        "t": _NUM, "drone": {"type": "string"}, "role": {"type": ["string", "null"]},
        "actor": {"type": ["string", "null"]}, "state": {"type": "string"},
        "position": {"type": ["array", "null"], "items": _NUM}, "setpoint": {"type": ["array", "null"], "items": _NUM},
        "setpoint_age": {"type": ["number", "null"]}, "battery": {"type": ["number", "null"]},
        "link_quality": {"type": ["number", "null"]}, "telemetry_age": _NUM}},
    "swarmpursuit.Setpoint": {"title": "swarmpursuit.Setpoint", "type": "object", "properties": {
        "t": _NUM, "drone": {"type": "string"}, "velocity": _ARR(_NUM), "age": {"type": ["number", "null"]}}},
    "swarmpursuit.Event": {"title": "swarmpursuit.Event", "type": "object", "properties": {
        "t": _NUM, "event": {"type": "string"}, "drone": {"type": ["string", "null"]}, "detail": {"type": "string"}}},
    "swarmpursuit.Metrics": {"title": "swarmpursuit.Metrics", "type": "object", "properties": {
        "t": _NUM, "mean_min_dist": _NUM, "mean_avg_dist": _NUM, "mean_max_dist": _NUM, "tracking_rate": _NUM,
        "coverage": _NUM, "episodes": {"type": "integer"}, "steps": {"type": "integer"}}},
    "swarmpursuit.Scene": {"title": "swarmpursuit.Scene", "type": "object", "properties": {
        "t": _NUM, "scene": {"type": "object"}}},
}
NON_EVENTS = ("scene", "metrics")
"""Event kinds that are data, not things that happened (their own channels; not on ``/log``)."""


def _time(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _pose(x: float, y: float, z: float) -> dict:
    return {"position": {"x": x, "y": y, "z": z}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def _rgba(r: float, g: float, b: float, a: float) -> dict:
    return {"r": r, "g": g, "b": b, "a": a}


def _entity(eid: str, ns: int, **prims: list) -> dict:
    e = {"timestamp": _time(ns), "frame_id": "world", "id": eid, "lifetime": {"sec": 0, "nsec": 0},
         "frame_locked": False, "metadata": [], "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "lines": [],
         "triangles": [], "texts": [], "models": []}
    e.update(prims)
    return e


def scene_entities(scene: dict, ns: int) -> list[dict]:
    """The fence (solid), the safe polygon inside its margin (thin), keep-out cylinders and anchor cubes."""
    fence = scene["fence"]
    z0, z1 = fence["z_band"]
    loop = lambda pts, z: [{"x": p[0], "y": p[1], "z": z} for p in pts]  # noqa: E731
    red = _rgba(0.84, 0.15, 0.16, 1.0)
    out = [_entity("fence", ns, lines=[
        {"type": 1, "pose": _pose(0, 0, 0), "thickness": 3.0, "scale_invariant": True,
         "points": loop(fence["polygon"], z), "color": red, "colors": [], "indices": []} for z in (0.0, z1)] + [
        {"type": 1, "pose": _pose(0, 0, 0), "thickness": 1.0, "scale_invariant": True,
         "points": loop(fence["safe_polygon"], z0 + fence["margin"]), "color": _rgba(0.84, 0.15, 0.16, 0.5),
         "colors": [], "indices": []}])]
    for k, ko in enumerate(scene.get("keep_out", [])):
        out.append(_entity(f"keep_out/{k}", ns, cylinders=[
            {"pose": _pose(ko["x"], ko["y"], z1 / 2), "size": {"x": 2 * ko["radius"], "y": 2 * ko["radius"], "z": z1},
             "bottom_scale": 1.0, "top_scale": 1.0, "color": _rgba(0.5, 0.5, 0.5, 0.6)}]))
    for a in scene.get("anchors", []):
        x, y, z = a["position"]
        out.append(_entity(f"anchor/{a['id']}", ns, cubes=[
            {"pose": _pose(x, y, z), "size": {"x": 0.1, "y": 0.1, "z": 0.1}, "color": _rgba(0.48, 0.25, 0.75, 1.0)}]))
    return out


def drone_entity(row: dict, ns: int) -> dict:
    x, y, z = row["position"]
    color = _rgba(*ROLE_RGBA.get(row.get("role"), ROLE_RGBA[None]))
    return _entity(f"drone/{row['drone']}", ns,
                   metadata=[{"key": k, "value": str(row.get(k))} for k in ("role", "actor", "state")],
                   spheres=[{"pose": _pose(x, y, z), "size": {"x": DRONE_SIZE, "y": DRONE_SIZE, "z": DRONE_SIZE},
                             "color": color}],
                   texts=[{"pose": _pose(x, y, z + 0.15), "billboard": True, "font_size": 14.0,
                           "scale_invariant": True, "color": _rgba(0.1, 0.1, 0.1, 1.0),
                           "text": f"{row['drone']} {row.get('role') or ''} {row.get('state')}"}])


# ---- the writer ----------------------------------------------------------------------------------

class McapRecorder:
    """Writes flight-log rows to an MCAP file (see the module docstring for the channels); thread-safe, keeps
    the rows like ``JsonlRecorder`` (``keep``). ``close`` writes the summary."""

    def __init__(self, path: str | Path, keep: bool = True, chunk_size: int = 64 * 1024) -> None:
        from mcap.writer import CompressionType, Writer
        self.path = Path(path)
        self.keep = keep
        self.rows: list[dict] = []
        self.counts: dict[str, int] = {}
        """Messages written per topic."""
        self._lock = threading.Lock()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = self.path.open("wb")
        self._writer = Writer(self._fh, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="swarmpursuit groundstation.mcap_log")
        self._schemas = {name: self._writer.register_schema(name, "jsonschema", json.dumps(s).encode())
                         for name, s in SCHEMAS.items()}
        self._channels: dict[str, int] = {}
        self._t0_ns: int | None = None
        self._poses: tuple[float, list] | None = None

    def _channel(self, topic: str, schema: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            cid = self._channels[topic] = self._writer.register_channel(topic, "json", self._schemas[schema])
        return cid

    def _put(self, topic: str, schema: str, ns: int, msg: dict) -> None:
        data = json.dumps(msg, separators=(",", ":"), default=str).encode()
        self._writer.add_message(self._channel(topic, schema), log_time=ns, data=data, publish_time=ns,
                                 sequence=self.counts.get(topic, 0))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def __call__(self, row: dict) -> None:
        with self._lock:
            if self._fh is None:
                return
            if self.keep:
                self.rows.append(row)
            t = float(row.get("t", 0.0))
            if self._t0_ns is None:
                self._t0_ns = time.time_ns() - int(t * 1e9)
            ns = self._t0_ns + int(round(t * 1e9))
            if "event" in row:
                self._event(row, ns)
            else:
                self._state(row, t, ns)

    def _event(self, row: dict, ns: int) -> None:
        kind = row["event"]
        if kind == "scene":
            self._put("/scene/static", "swarmpursuit.Scene", ns, row)
            self._put("/scene", "foxglove.SceneUpdate", ns,
                      {"deletions": [], "entities": scene_entities(row["scene"], ns)})
            return
        if kind == "metrics":
            self._put("/metrics", "swarmpursuit.Metrics", ns, row)
            return
        self._put("/events", "swarmpursuit.Event", ns, row)
        level = LOG_ERROR if kind in ERROR_EVENTS else LOG_WARNING if kind in WARNING_EVENTS else LOG_INFO
        drone = row.get("drone")
        self._put("/log", "foxglove.Log", ns, {
            "timestamp": _time(ns), "level": level, "name": drone or "swarm-gs",
            "message": f"{drone + ' ' if drone else ''}{kind}" + (f": {row['detail']}" if row.get("detail") else ""),
            "file": "", "line": 0})

    def _state(self, row: dict, t: float, ns: int) -> None:
        drone = row["drone"]
        self._put(f"/drones/{drone}/status", "swarmpursuit.DroneStatus", ns, row)
        if row.get("setpoint") is not None:
            self._put(f"/drones/{drone}/setpoint", "swarmpursuit.Setpoint", ns,
                      {"t": row["t"], "drone": drone, "velocity": row["setpoint"], "age": row.get("setpoint_age")})
        if row.get("position") is None:
            return
        self._put("/scene", "foxglove.SceneUpdate", ns, {"deletions": [], "entities": [drone_entity(row, ns)]})
        # every drone's pose at one record time: the rows of one period share their t
        if self._poses is not None and self._poses[0] != t:
            self._flush_poses()
        if self._poses is None:
            self._poses = (t, [])
        self._poses[1].append((ns, row["position"]))

    def _flush_poses(self) -> None:
        if not self._poses or not self._poses[1]:
            self._poses = None
            return
        ns = self._poses[1][0][0]
        self._put("/drones/poses", "foxglove.PosesInFrame", ns,
                  {"timestamp": _time(ns), "frame_id": "world", "poses": [_pose(*p) for _, p in self._poses[1]]})
        self._poses = None

    def close(self) -> None:
        with self._lock:
            if self._fh is None:
                return
            self._flush_poses()
            self._writer.finish()
            self._fh.close()
            self._fh = None


def open_recorder(path: str | Path | None, scene: dict | None = None, keep: bool = True):
    """The flight-log recorder for ``path`` by its suffix: ``.mcap`` -> ``McapRecorder``, else (``.jsonl``, or
    None: rows kept in memory only) ``JsonlRecorder``. With ``scene`` (``liveview.scene``) its first row is the
    ``scene`` event, so that a replay draws the fence, keep-outs and anchors."""
    rec = McapRecorder(path, keep=keep) if path is not None and str(path).lower().endswith(".mcap") \
        else JsonlRecorder(path, keep=keep)
    if scene is not None:
        rec({"t": 0.0, "event": "scene", "drone": None, "detail": "", "scene": scene})
    return rec


# ---- reading -------------------------------------------------------------------------------------

class LogError(ValueError):
    """A flight log that cannot be read; the message names the file and what is wrong."""


def read_log(path: str | Path) -> list[dict]:
    """The rows of a flight log, JSON lines or MCAP (by suffix), in the order written. An MCAP log gives back
    its ``/drones/*/status``, ``/events``, ``/metrics`` and ``/scene/static`` messages: the rows as written."""
    p = Path(path)
    if not p.is_file():
        raise LogError(f"{p}: no such flight log: give the file that --log wrote")
    if p.suffix.lower() == ".mcap":
        return _read_mcap(p)
    rows = []
    with p.open() as fh:
        for k, line in enumerate(fh, 1):
            if not line.strip():
                continue
            try:
                rows.append(json.loads(line))
            except ValueError:
                if k > 1 and not line.endswith("\n"):  # the last line of a log cut short mid-write
                    break
                raise LogError(f"{p}:{k}: not a JSON-lines flight log row: {line[:60]!r}") from None
    return rows


WANTED = ("/events", "/metrics", "/scene/static")


def _wanted(topic: str) -> bool:
    return topic in WANTED or (topic.startswith("/drones/") and topic.endswith("/status"))


def _read_mcap(p: Path) -> list[dict]:
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader
    with p.open("rb") as fh:
        try:
            return [json.loads(m.data) for _s, c, m in make_reader(fh).iter_messages(log_time_order=True)
                    if _wanted(c.topic)]
        except (McapError, ValueError, EOFError) as exc:
            first = exc
    # no summary or footer: a flight cut short (Ctrl-C, a killed process). Read its records in file order up to
    # where the file ends (the chunks written before the cut).
    rows: list[dict] = []
    topics: dict[int, str] = {}
    with p.open("rb") as fh:
        try:
            for rec in StreamReader(fh).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Message) and _wanted(topics.get(rec.channel_id, "")):
                    rows.append(json.loads(rec.data))
        except (McapError, ValueError, EOFError) as exc:
            if not rows:
                raise LogError(f"{p}: not a readable MCAP flight log: {first}") from None
            log.warning("%s: ends without its summary (%s): the flight log was cut short; read %d rows",
                        p, exc, len(rows))
    return sorted(rows, key=lambda r: float(r.get("t", 0.0)))
