"""Models and helpers for the flight tests.

``write_models`` writes a models folder in the exact format of ``swarm-export onnx`` (one ONNX actor per
agent with the spec metadata, ``manifest.json`` with sha256s) without torch: each actor is a small
tanh MLP built with ``onnx.helper`` from seeded random weights, which takes milliseconds instead of the
exporter's tracing. ``nan_actors`` get NaN weights (an actor whose output is never finite).
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from runtime.spec import SwarmSpec


def _actor(spec: SwarmSpec, agent_id: str, role, rng: np.random.Generator, hidden: int, nan: bool) -> onnx.ModelProto:
    d = spec.obs_dim(role)
    w1 = (rng.standard_normal((d, hidden)) / np.sqrt(d)).astype(np.float32)
    w2 = (rng.standard_normal((hidden, spec.act_dim)) / np.sqrt(hidden)).astype(np.float32)
    if nan:
        w2[:] = np.nan
    inits = [numpy_helper.from_array(w1, "w1"), numpy_helper.from_array(np.zeros(hidden, np.float32), "b1"),
             numpy_helper.from_array(w2, "w2"), numpy_helper.from_array(np.zeros(spec.act_dim, np.float32), "b2")]
    nodes = [helper.make_node("MatMul", ["obs", "w1"], ["h0"]), helper.make_node("Add", ["h0", "b1"], ["h1"]),
             helper.make_node("Tanh", ["h1"], ["h"]), helper.make_node("MatMul", ["h", "w2"], ["a0"]),
             helper.make_node("Add", ["a0", "b2"], ["a1"]), helper.make_node("Tanh", ["a1"], ["action"])]
    graph = helper.make_graph(nodes, agent_id, [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", d])],
                              [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", spec.act_dim])],
                              inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    meta = {"spec_hash": spec.hash, "role": role.label, "agent_id": agent_id,
            "spec_json": json.dumps(spec.to_dict(), sort_keys=True), "obs_dim": str(d), "act_dim": str(spec.act_dim)}
    for k, v in meta.items():
        e = model.metadata_props.add()
        e.key, e.value = k, v
    onnx.checker.check_model(model)
    return model


def write_models(out: Path, spec: SwarmSpec | None = None, seed: int = 0, hidden: int = 32,
                 nan_actors: tuple[str, ...] = ()) -> Path:
    """A models folder for ``spec`` (default ``SwarmSpec()``) in ``out``; returns ``out``."""
    spec = spec or SwarmSpec()
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    entries = []
    for agent_id, role in zip(spec.team.agent_ids(), spec.roles):
        path = out / f"{agent_id}.onnx"
        path.write_bytes(_actor(spec, agent_id, role, rng, hidden, agent_id in nan_actors).SerializeToString())
        entries.append({"id": agent_id, "role": role.label, "file": path.name,
                        "sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "obs_dim": spec.obs_dim(role)})
    manifest = {"format": 1, "spec_hash": spec.hash, "spec": spec.to_dict(), "agents": entries,
                "config": {"note": "random test actors (tests/flight_fixtures.py)"}, "evaluation": None}
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return out


# ---- simulated fleets -----------------------------------------------------------------------------

def small_spec() -> SwarmSpec:
    """2 pursuers, 2 scouts, 1 evader: the smallest team with every role, for quick flights."""
    return SwarmSpec.from_dict({"team": {"n_pursuers": 2, "n_scouts": 2, "n_evaders": 1}})


def quick_flight(**overrides):
    """Flight settings for short test flights (low, quick takeoff and landing)."""
    from groundstation.flight import FlightConfig
    base = dict(QUICK_FLIGHT)
    base.update(overrides)
    return FlightConfig(**base)


QUICK_FLIGHT = dict(height=0.5, takeoff_duration=1.0, takeoff_stagger=0.05, land_speed=0.5)
"""``quick_flight``'s settings: what a test flight needs of takeoff and landing, not a demo's pace."""


def quick_flight_toml(path, **extra) -> "Path":
    """A [flight] TOML with ``quick_flight``'s settings (and ``extra``), for ``swarm-gs demo --flight-config``."""
    from pathlib import Path
    path = Path(path)
    body = {**QUICK_FLIGHT, **extra}
    path.write_text("[flight]\n" + "".join(f"{k} = {v!r}\n" for k, v in body.items()))
    return path


def open_sim_links(uris: list[str], period_ms: int = 20) -> list:
    """CflibLinks to simulated drones, opened in parallel."""
    import concurrent.futures

    from groundstation.fleet import TOC_CACHE  # the TOC downloaded once (by CRC), not once per test
    from groundstation.link import open_link
    with concurrent.futures.ThreadPoolExecutor(len(uris)) as ex:
        return list(ex.map(lambda u: open_link(u, period_ms=period_ms, rw_cache=str(TOC_CACHE)), uris))


def wait_until(predicate, timeout: float, period: float = 0.01) -> bool:
    import time
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period)
    return bool(predicate())


def stream(send, seconds: float, rate_hz: float = 50.0) -> None:
    """Call ``send()`` at ``rate_hz`` for ``seconds`` (a setpoint stream)."""
    import time
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        send()
        time.sleep(1.0 / rate_hz)


def stream_until(send, predicate, timeout: float, rate_hz: float = 50.0) -> bool:
    """Call ``send()`` at ``rate_hz`` until ``predicate()`` holds (True) or ``timeout`` [s] passes (False)."""
    import time
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        send()
        if predicate():
            return True
        time.sleep(1.0 / rate_hz)
    return bool(predicate())


def on_ground(truth, z: float = 0.05) -> bool:
    """A simulated drone's ground truth says it is down with its motors off."""
    return truth.position[2] <= z and not truth.motors_on


class ScriptedLink:
    """A ``Link`` whose telemetry the test publishes itself (for supervisor logic without a simulator).
    Commands are recorded in ``sent``."""

    def __new__(cls, uri: str):
        from groundstation.link import Link, LinkStats

        class _Scripted(Link):
            def __init__(self, uri: str) -> None:
                super().__init__(uri)
                self.sent: list[tuple] = []

            def feed(self, t: float, position=(0.0, 0.0, 0.5), flight_state=None, battery: float = 4.0):
                from groundstation.link import FlightState, Telemetry
                self._publish(Telemetry(t=t, position=tuple(position), velocity=(0.0, 0.0, 0.0), battery=battery,
                                        link_quality=1.0, flight_state=flight_state or FlightState.FLYING))

            def send_velocity(self, vx, vy, vz, yaw_rate=0.0):
                self.sent.append(("velocity", vx, vy, vz))

            def send_position(self, x, y, z, yaw=0.0):
                self.sent.append(("position", x, y, z))

            def takeoff(self, height, duration):
                self.sent.append(("takeoff", height, duration))

            def land(self, duration, height=0.0):
                self.sent.append(("land", duration, height))

            def emergency_stop(self):
                self.sent.append(("emergency_stop",))

            def stats(self):
                return LinkStats(len(self.sent), 0, self._telemetry_count, self.telemetry_age(), self.link_lost,
                                 self._opened_at)

            def close(self):
                pass

        return _Scripted(uri)


def write_fleet(path, models, spec_toml, uris, root, evader: int = 2):
    """A fleet file at ``path`` for simulated drones at ``uris`` (drone ``evader`` on the evader team), with the
    repository's fence and anchors under ``root`` and a quick flight; returns the path."""
    from pathlib import Path
    drones = "".join(f'[[fleet.drones]]\nid = "cf{i}"\nuri = "{u}"\nteam = "{"evader" if i == evader else "pursuer"}"\n'
                     for i, u in enumerate(uris))
    path = Path(path)
    path.write_text(f'[fleet]\nmodels = "{models}"\nspec = "{spec_toml}"\n'
                    f'fence = "{root / "configs" / "fence.toml"}"\n'
                    f'anchors = "{root / "configs" / "lps_anchors.toml"}"\n{drones}'
                    "[flight]\nheight = 0.5\ntakeoff_duration = 1.0\ntakeoff_stagger = 0.05\nland_speed = 0.5\n")
    return path
