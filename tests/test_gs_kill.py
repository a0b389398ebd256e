"""No drone flies uncommanded: the ground-station process is killed (SIGKILL) at random moments of a short
flight, takeoff and landing included, and every simulated drone must be down and locked within 3 s.

The simulated Crazyflies run in this process (``SimSwarm``, ground truth read directly); the ground station
is a separate Python process flying them through unmodified cflib and ``FlightSession`` (the script below;
the next one starts while the previous one's drones come down, to keep the test short).
It prints each phase as it starts; the kill moment is then chosen by an event in the simulator (a drone
climbing past a random height, a random number of packets received, a drone descending past a random
height), so the test never sleeps for a fixed time. What brings the drones down is the firmware's own
emergency-stop watchdog that ``CflibLink`` arms and feeds: nothing in the killed process runs any more.
A frozen ground station (SIGSTOP) and an unplugged radio (the simulator stops hearing it) end the same way.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cflib")

from flight_fixtures import on_ground, wait_until  # noqa: E402
from groundstation.sim.swarm import SimSwarm, free_base_port  # noqa: E402

N = 3
DOWN_WITHIN_S = 3.0
TESTS = Path(__file__).resolve().parent

GROUND_STATION = """
import concurrent.futures, sys, time
from groundstation.flight import FlightConfig, FlightSession
from groundstation.link import open_link
from groundstation.safety import FenceConfig

cache, uris = sys.argv[1], sys.argv[2:]
ids = [f"cf{i}" for i in range(len(uris))]
with concurrent.futures.ThreadPoolExecutor(len(uris)) as ex:
    links = list(ex.map(lambda u: open_link(u, period_ms=20, rw_cache=cache), uris))
config = FlightConfig(height=0.5, takeoff_duration=1.5, takeoff_stagger=0.1, land_speed=0.5)
session = FlightSession(dict(zip(ids, links)), {d: "pursuer" for d in ids}, FenceConfig(), config)
with session:
    session.preflight()
    print("PHASE takeoff", flush=True)
    session.takeoff()
    print("PHASE mission", flush=True)
    session.start_mission()
    time.sleep(2.0)  # the mission: hover
    print("PHASE landing", flush=True)
    session.land_all()
print("PHASE done", flush=True)
"""


def _z(sims: SimSwarm) -> np.ndarray:
    return np.array([sims.truth(i).position[2] for i in range(sims.n)])


def _moments(rng: np.random.Generator) -> list[tuple[str, str, object]]:
    """(phase, what triggers the kill, its random parameter)."""
    return [
        ("takeoff", "at once", None),  # between the staggered takeoff commands
        ("takeoff", "climbing past", float(rng.uniform(0.03, 0.35))),
        ("mission", "packets", int(rng.integers(5, 50))),
        ("landing", "descending past", float(rng.uniform(0.2, 0.4))),
    ]


def _trigger(sims: SimSwarm, kind: str, param) -> bool:
    if kind == "at once":
        return True
    if kind == "climbing past":
        return bool(np.max(_z(sims)) > param)
    if kind == "descending past":
        return bool(np.min(_z(sims)) < param)
    raise ValueError(kind)


def _read_until(proc: subprocess.Popen, phase: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise AssertionError(f"the ground station exited before {phase}: {proc.stderr.read()[-2000:]}")
        if line.strip() == f"PHASE {phase}":
            return
    raise AssertionError(f"no PHASE {phase} within {timeout} s")


class _Run:
    """One simulated swarm and one ground-station process flying it."""

    def __init__(self, seed: int, cache: Path) -> None:
        self.sims = SimSwarm(N, base_port=free_base_port(N, seed=seed), seed=seed).start()
        self.proc = subprocess.Popen([sys.executable, "-c", GROUND_STATION, str(cache), *self.sims.uris],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     env=dict(os.environ, PYTHONUNBUFFERED="1"))

    def kill_at(self, phase: str, kind: str, param, how: str = "killed") -> None:
        sims = self.sims
        _read_until(self.proc, phase, timeout=90.0)
        if kind == "packets":
            start = sims.packet_counts()[0][0]
            assert wait_until(lambda: sims.packet_counts()[0][0] - start >= param, 10.0)
        else:
            assert wait_until(lambda: _trigger(sims, kind, param), 10.0), f"{kind} {param} never happened"
        self.airborne = [i for i in range(N) if sims.truth(i).position[2] > 0.02]
        if how == "killed":
            self.proc.send_signal(signal.SIGKILL)
        elif how == "frozen":
            self.proc.send_signal(signal.SIGSTOP)  # every thread stops, the process stays
        else:  # the radio unplugged: nothing reaches the drones any more, the ground station runs on
            for i in range(N):
                sims.kill_link(i)
        self.t_kill = time.monotonic()

    def outcome(self) -> dict:
        sims = self.sims
        armed = [i for i in range(N) if sims.truth(i).watchdog_armed]

        def safe() -> bool:
            return all(on_ground(sims.truth(i)) for i in range(N)) and all(sims.is_locked(i) for i in armed)

        wait_until(safe, 3 * DOWN_WITHIN_S)
        return {"elapsed": time.monotonic() - self.t_kill, "safe": safe(), "airborne": self.airborne,
                "armed": armed, "truth": [sims.truth(i) for i in range(N)], "contacts": sims.drone_contacts}

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.kill()
            self.proc.wait(timeout=10.0)
        self.sims.stop()


def test_a_killed_ground_station_leaves_every_drone_down_and_locked_within_3_s(tmp_path):
    seed = int.from_bytes(os.urandom(4), "little")
    rng = np.random.default_rng(seed)
    moments = _moments(rng)
    runs: list[_Run] = []
    outcomes = []
    try:
        runs.append(_Run(seed, tmp_path))
        for k, (phase, kind, param) in enumerate(moments):
            run = runs[k]
            run.kill_at(phase, kind, param)
            if k + 1 < len(moments):  # the next ground station starts up while this one's drones come down
                runs.append(_Run(seed + k + 1, tmp_path))
            out = run.outcome()
            run.close()
            where = f"seed {seed}: killed in {phase} ({kind} {param})"
            assert out["safe"], f"{where}: not down and locked: {out['truth']}"
            assert out["elapsed"] <= DOWN_WITHIN_S, f"{where}: down and locked only after {out['elapsed']:.2f} s"
            # every drone that was commanded to fly was put under the watchdog, airborne ones in particular;
            # one never commanded rests, ready, on the ground
            assert set(out["airborne"]) <= set(out["armed"]), where
            assert all(t.supervisor == "locked" or (i not in out["armed"] and t.supervisor == "ready")
                       for i, t in enumerate(out["truth"])), where
            assert out["contacts"] == 0, where
            outcomes.append((phase, len(out["airborne"])))
    finally:
        for run in runs:
            run.close()
    # the moments covered drones in the air, during takeoff as well as after it
    assert outcomes[1][1] > 0 and outcomes[2][1] == N and outcomes[3][1] == N, outcomes


@pytest.mark.parametrize("how,phase,kind,param", [("frozen", "takeoff", "climbing past", 0.1),
                                                  ("unplugged", "landing", "descending past", 0.35)])
def test_a_frozen_or_unplugged_ground_station_leaves_every_drone_down_and_locked(tmp_path, how, phase, kind,
                                                                                  param):
    run = _Run(int.from_bytes(os.urandom(4), "little") % 1000, tmp_path)
    try:
        run.kill_at(phase, kind, param, how=how)
        out = run.outcome()
    finally:
        run.close()
    assert out["safe"] and out["elapsed"] <= DOWN_WITHIN_S, out
    assert out["airborne"] and set(out["airborne"]) <= set(out["armed"])
