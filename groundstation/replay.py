"""``swarm-gs replay`` and ``swarm-gs report``: a flight log (JSON lines or MCAP, ``mcap_log.read_log``) played
into the live page, and the paper's metrics and the trajectory picture from it.

``ReplaySource`` is a live-view source (``liveview.LiveView.attach``) whose state is the log at the replay
clock: each drone's latest state row at or before it, the events so far, the latest metrics row. Its one
control, ``POST /api/replay`` with ``{"pause": bool, "seek": s, "speed": x}``, moves that clock; the page's
replay bar sends it.

``report`` recomputes the paper's metrics (``demo_metrics.EpisodeMetrics`` over ``runtime.metrics``) from the logged
positions: one step per record period (the flight log is written at the control rate, 10 Hz), agents in spec
order at the position of the drone flying each actor. The team comes from the actors named in the log, the
arena, sensing range and obstacles from its ``scene`` row.
"""
from __future__ import annotations

import bisect
import math
import threading
import time
from typing import Any

import numpy as np

from groundstation.liveview.server import ControlRefused
from groundstation.mcap_log import LogError

MAX_EVENTS = 100
"""Events the page gets per state (the latest ones)."""


def _split(rows: list[dict]) -> tuple[dict | None, list[dict], list[dict], list[dict]]:
    """(scene, state rows, event rows, metrics rows) of a log."""
    scene = next((r.get("scene") for r in rows if r.get("event") == "scene"), None)
    state = [r for r in rows if "event" not in r and "drone" in r]
    events = [r for r in rows if "event" in r and r["event"] not in ("scene", "metrics")]
    metrics = [r for r in rows if r.get("event") == "metrics"]
    return scene, state, events, metrics


def _status_changes(events: list[dict]) -> dict[str, tuple[list[float], list[str]]]:
    """Drone -> (times, statuses) of its status events: a status can change between two record periods (the
    last rows of a flight are often written before the touchdown)."""
    out: dict[str, tuple[list[float], list[str]]] = {}
    for e in events:
        if e["event"] == "status" and e.get("drone") and e.get("to"):
            ts, ss = out.setdefault(e["drone"], ([], []))
            ts.append(float(e["t"]))
            ss.append(e["to"])
    return out


def _status_at(row: dict, changes: tuple[list[float], list[str]] | None, t: float) -> str:
    """The drone's status at ``t``: its state row's, unless a status event came after that row."""
    if changes is not None:
        k = bisect.bisect_right(changes[0], t) - 1
        if k >= 0 and changes[0][k] > float(row["t"]):
            return changes[1][k]
    return row.get("state")


class ReplaySource:
    """A flight log as a live-view source (see the module docstring). ``speed``: replay time per wall time."""

    controls = ("replay",)

    def __init__(self, rows: list[dict], speed: float = 1.0, start: float = 0.0) -> None:
        if not (speed > 0 and math.isfinite(speed)):
            raise ValueError(f"--speed: must be > 0, got {speed!r}")
        self.scene, state, events, metrics = _split(rows)
        if not state:
            raise LogError("the log has no drone rows (state rows with a drone): nothing to replay")
        self.ids = list(dict.fromkeys(r["drone"] for r in state))
        self._rows = {d: [r for r in state if r["drone"] == d] for d in self.ids}
        self._times = {d: [float(r["t"]) for r in self._rows[d]] for d in self.ids}
        self._events = sorted(events, key=lambda r: float(r["t"]))
        self._event_t = [float(r["t"]) for r in self._events]
        self._metrics = sorted(metrics, key=lambda r: float(r["t"]))
        self._metric_t = [float(r["t"]) for r in self._metrics]
        self._changes = _status_changes(self._events)
        self.t_begin = min(min(ts) for ts in self._times.values())
        t_end = max(max(ts) for ts in self._times.values())
        if self._event_t:  # the landings after the last record period
            t_end = max(t_end, self._event_t[-1])
        self.duration = t_end - self.t_begin
        self.speed = float(speed)
        self.paused = False
        self._lock = threading.Lock()
        self._base = min(max(start, 0.0), self.duration)
        self._wall = time.monotonic()

    # -- the replay clock -------------------------------------------------------------------------

    def position(self) -> float:
        """Replay time since the log's first row [s]."""
        with self._lock:
            if self.paused:
                return self._base
            return min(self._base + (time.monotonic() - self._wall) * self.speed, self.duration)

    @property
    def finished(self) -> bool:
        return self.position() >= self.duration

    def _set(self, t: float) -> None:
        self._base, self._wall = min(max(t, 0.0), self.duration), time.monotonic()

    def control(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        if name != "replay":
            raise ControlRefused(f"{name}: a replay has no drones to command (its control is replay)")
        now = self.position()
        with self._lock:
            if "speed" in args:
                v = args["speed"]
                if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                    raise ControlRefused(f"speed: must be a number > 0, got {v!r}")
                self.speed = float(v)
                self._set(now)
            if "seek" in args:
                v = args["seek"]
                if not (isinstance(v, (int, float)) and math.isfinite(v)):
                    raise ControlRefused(f"seek: must be a time in s, got {v!r}")
                self._set(float(v))
                now = self._base
            if "pause" in args:
                self.paused = bool(args["pause"])
                self._set(now)
        return {"ok": True, "control": name, "replay": self._clock()}

    def _clock(self) -> dict[str, Any]:
        """The clock for the page's replay bar (call with the lock held)."""
        t = self._base if self.paused else min(self._base + (time.monotonic() - self._wall) * self.speed,
                                               self.duration)
        return {"t": round(t, 3), "duration": round(self.duration, 3), "paused": self.paused, "speed": self.speed}

    # -- the state --------------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        pos = self.position()
        t = self.t_begin + pos
        drones = []
        for d in self.ids:
            k = bisect.bisect_right(self._times[d], t) - 1
            if k < 0:
                continue
            r = self._rows[d][k]
            drones.append({"id": d, "team": r.get("team"), "role": r.get("role"), "actor": r.get("actor"),
                           "status": _status_at(r, self._changes.get(d), t), "reason": "", "position": r.get("position"),
                           "battery": r.get("battery"), "link_quality": r.get("link_quality"),
                           "position_variance": r.get("position_variance"), "setpoint": r.get("setpoint"),
                           "setpoint_age": r.get("setpoint_age"), "command_age": r.get("command_age"),
                           "telemetry_age": r.get("telemetry_age")})
        n = bisect.bisect_right(self._event_t, t)
        events = [{"i": i, "t": float(e["t"]), "drone": e.get("drone"), "kind": e["event"],
                   "detail": e.get("detail", "")} for i, e in zip(range(max(n - MAX_EVENTS, 0), n),
                                                                  self._events[max(n - MAX_EVENTS, 0):n])]
        kinds = [e["kind"] for e in events]
        mission = "mission_start" in kinds and (kinds[::-1].index("mission_start") <
                                                (kinds[::-1].index("mission_end") if "mission_end" in kinds
                                                 else len(kinds)))
        m = bisect.bisect_right(self._metric_t, t) - 1
        metrics = {k: v for k, v in self._metrics[m].items() if k not in ("t", "event", "drone", "detail")} \
            if m >= 0 else {}
        with self._lock:
            clock = self._clock()
        return {"mode": "replay", "t": round(t, 4), "mission": mission, "drones": drones, "events": events,
                "n_events": n, "scene": self.scene, "metrics": metrics, "controls": list(self.controls),
                "replay": clock}


# ---- report --------------------------------------------------------------------------------------

def _spec_from_log(state: list[dict], scene: dict | None):
    from runtime.spec import SwarmSpec
    actors = {r["actor"] for r in state if r.get("actor")}
    count = lambda role: sum(1 for a in actors if a.startswith(role + "_"))  # noqa: E731
    team = {"n_pursuers": count("pursuer"), "n_scouts": count("scout"), "n_evaders": count("evader")}
    if team["n_evaders"] == 0 or team["n_pursuers"] + team["n_scouts"] == 0:
        raise LogError("the log names no evader actor, or no pursuer or scout actor: the paper's metrics need both "
                       "(was it a flight with actors, swarm-gs demo or fly?)")
    data: dict[str, Any] = {"team": team}
    if scene is not None and scene.get("sensing_range"):
        data["sensing"] = {"sensing_range": scene["sensing_range"]}
    if scene is not None and scene.get("arena"):
        data["arena"] = {"half_width": scene["arena"]["half_width"]}
    return SwarmSpec.from_dict(data)


def _final_states(state: list[dict], events: list[dict]) -> dict[str, str]:
    changes = _status_changes(events)
    out = {}
    for d in dict.fromkeys(r["drone"] for r in state):
        last = next(r for r in reversed(state) if r["drone"] == d)
        out[d] = _status_at(last, changes.get(d), math.inf)
    return out


def report(rows: list[dict]) -> dict[str, Any]:
    """The paper's metrics recomputed from a log's positions, with what the log says about the flight."""
    from groundstation.demo_metrics import EpisodeMetrics
    scene, state, events, metrics_rows = _split(rows)
    if not state:
        raise LogError("the log has no drone rows: nothing to report")
    spec = _spec_from_log(state, scene)
    obstacles = np.array([[k["x"], k["y"], k["radius"]] for k in (scene or {}).get("keep_out", [])],
                         dtype=float).reshape(-1, 3)
    agent_ids = list(spec.team.agent_ids())
    em = EpisodeMetrics(spec, obstacles)
    last = np.zeros((spec.n_agents, 2))
    seen = np.zeros(spec.n_agents, dtype=bool)
    by_t: dict[float, list[dict]] = {}
    for r in state:
        by_t.setdefault(float(r["t"]), []).append(r)
    steps = 0
    for t in sorted(by_t):
        present = np.zeros(spec.n_agents, dtype=bool)
        for r in by_t[t]:
            a = r.get("actor")
            if a in agent_ids and r.get("position") is not None and r.get("state") == "flying":
                i = agent_ids.index(a)
                last[i] = r["position"][:2]
                present[i] = seen[i] = True
        if present.any() and seen.all():  # every actor placed once: the mission is on
            em(t, last.copy(), np.zeros_like(last), present)
            steps += 1
    out: dict[str, Any] = {"team": {"pursuers": spec.team.n_pursuers, "scouts": spec.team.n_scouts,
                                    "evaders": spec.team.n_evaders}, "steps": steps}
    out.update(em.summary() if steps else {"episodes": 0})
    ids = list(dict.fromkeys(r["drone"] for r in state))
    final = _final_states(state, events)
    out.update({
        "drones": len(ids), "final_state": final, "landed": sum(1 for s in final.values() if s == "landed"),
        "duration_s": round(max(by_t) - min(by_t), 2),
        "failsafes": [f"t={float(e['t']):.2f} s {e.get('drone') or ''} {e['event']}: {e.get('detail', '')}"
                      for e in events if e["event"] in ("link_lost", "low_battery", "agent_fault", "fence_breach",
                                                        "position_invalid", "emergency_stop", "dropped", "abort")],
        "logged_metrics": {k: v for k, v in metrics_rows[-1].items() if k not in ("t", "event", "drone", "detail")}
        if metrics_rows else None,
    })
    return out


def format_report(res: dict[str, Any]) -> str:
    f = lambda v, d=3: "-" if v is None else (f"{v:.{d}f}" if isinstance(v, float) else str(v))  # noqa: E731
    t = res["team"]
    lines = [f"{res['drones']} drones ({t['pursuers']} pursuers, {t['scouts']} scouts, {t['evaders']} evaders), "
             f"{res['duration_s']} s logged, {res['steps']} mission steps, {res.get('episodes', 0)} episode(s)",
             f"distance to targets  min {f(res.get('mean_min_dist'))}  mean {f(res.get('mean_avg_dist'))}  "
             f"max {f(res.get('mean_max_dist'))} m",
             f"tracking rate {f(res.get('tracking_rate'))}   coverage {f(res.get('coverage'))}   "
             f"captures/episode {f(res.get('captures_per_episode'), 2)}",
             f"landed {res['landed']}/{res['drones']}   final: " + ", ".join(f"{d} {s}" for d, s in
                                                                            res["final_state"].items())]
    lines += [f"  {x}" for x in res["failsafes"]]
    return "\n".join(lines)


def plot_log(path: str, rows: list[dict]) -> None:
    """The demo's trajectory picture (``demo_report.plot_flight``) from a log with a scene row."""
    from groundstation.demo_report import plot_flight
    from groundstation.positioning import Anchor, AnchorLayout
    from groundstation.safety import FenceConfig, KeepOut
    scene, state, _, _ = _split(rows)
    if scene is None:
        raise LogError("the log has no scene row (fence, keep-outs, anchors): written before swarm-gs logged it; "
                       "the trajectory picture needs it")
    fz = scene["fence"]
    fence = FenceConfig(vertices=tuple(tuple(p) for p in fz["polygon"]), z_min=fz["z_band"][0],
                        z_max=fz["z_band"][1], margin=fz["margin"],
                        keep_out=tuple(KeepOut(k["x"], k["y"], k["radius"]) for k in scene["keep_out"]))
    anchors = None
    if len(scene.get("anchors", [])) >= 4:
        anchors = AnchorLayout(anchors=tuple(Anchor(a["id"], tuple(a["position"]), "logged")
                                             for a in scene["anchors"]), expected_count=len(scene["anchors"]))
    ids = list(dict.fromkeys(r["drone"] for r in state))
    res = report(rows) if any(r.get("actor") for r in state) else {"drones": len(ids)}
    final = _final_states(state, _split(rows)[2])
    title = {"drones": len(ids), "mission_s": res.get("duration_s"),
             "landed": sum(1 for s in final.values() if s == "landed"), "geofence_violations": "-"}
    plot_flight(path, rows, fence, anchors, ids, {}, title)

