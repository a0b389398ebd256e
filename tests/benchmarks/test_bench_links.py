"""Ground-station links: measurement-to-setpoint latency for 12 drones through unmodified cflib, and packets
per second per link, against the simulated Crazyflies (CRTP over UDP on loopback).

Latency is measured at the drone: the simulator (``SimSwarm(latency_probe=True)``) notes when each log packet
(a measurement, stamped with the firmware's millisecond tick) leaves it; the ground station answers each
telemetry sample that arrives through ``CflibLink`` with a velocity setpoint that carries the sample's tick
(in the yaw-rate field, zero velocity otherwise); the simulator records when that setpoint arrives. So a
sample is: simulator socket -> cflib's UDP and packet-handler threads -> ``Link`` telemetry callback ->
``send_velocity`` -> cflib -> simulator socket. Setpoints are sent on every telemetry sample or at
``setpoint_hz`` (the flight layer's rate), whichever is slower.

Run (slow, not in the default suite):
    nice -n 15 .venv/bin/python -m pytest -q -s -m slow tests/benchmarks/test_bench_links.py
or standalone, printing JSON:
    nice -n 15 .venv/bin/python tests/benchmarks/test_bench_links.py --drones 12 --period-ms 20 --duration 10
"""
from __future__ import annotations

import argparse
import concurrent.futures
import json
import logging
import os
import platform
import tempfile
import threading
import time

import numpy as np
import pytest

P99_TARGET_MS = 10.0
"""Issue 5: measurement-to-setpoint p99 for 12 drones through cflib."""
RADIO_TRANSACTIONS_PER_S = 1000.0
"""Estimated budget of one Crazyradio driven by cflib: one radio transaction (a packet up, its ack with at most
one packet down) per USB round trip, and full-speed USB bulk transfers are scheduled in 1 ms frames. An
estimate, not measured here (no radio on this machine)."""


class _Sim:
    """The simulators in the ground station's interpreter (``SimSwarm``) or in a process of their own
    (``SimProcess``, as ``swarm-gs demo`` runs them)."""

    def __init__(self, n: int, base_port: int, in_process: bool) -> None:
        from groundstation.sim.remote import SimProcess
        from groundstation.sim.swarm import SimSwarm
        cls = SimSwarm if in_process else SimProcess
        self.sims = cls(n, base_port=base_port, seed=0, latency_probe=True).start()

    def report(self):
        return self.sims.latency_samples(), self.sims.packet_counts()

    def stop(self) -> None:
        self.sims.stop()


def measure(n: int = 12, period_ms: int = 20, setpoint_hz: float = 50.0, duration: float = 10.0,
            sim_in_process: bool = True, warmup: float = 1.0) -> dict:
    from groundstation.link import open_link
    from groundstation.sim.swarm import free_base_port

    logging.getLogger("groundstation.cflib_link").setLevel(logging.ERROR)  # "closing while flying" x 12

    base = free_base_port(n)
    sim = _Sim(n, base, sim_in_process)
    uris = [f"udp://127.0.0.1:{base + i}" for i in range(n)]
    cache = tempfile.mkdtemp(prefix="bench_links_cache_")
    links = []
    try:
        with concurrent.futures.ThreadPoolExecutor(n) as ex:
            links = list(ex.map(lambda u: open_link(u, period_ms=period_ms, rw_cache=cache), uris))
        active = threading.Event()
        gs_delays: list[float] = []
        # Answer every sample when setpoints are at least as fast as telemetry, else every k-th one.
        every = max(1, round(1000.0 / period_ms / setpoint_hz))

        def responder(link):
            count = [0]

            def on_sample(sample):
                count[0] += 1
                if not active.is_set() or count[0] % every:
                    return
                link.send_velocity(0.0, 0.0, 0.0, yaw_rate=float(sample.vehicle_time_ms & 0xFFFF))
                gs_delays.append(time.monotonic() - sample.t)
            return on_sample

        callbacks = [responder(link) for link in links]
        for link, cb in zip(links, callbacks):
            link.add_telemetry_callback(cb)
        active.set()
        time.sleep(warmup)
        lat0, pk0 = sim.report()
        s0 = [link.stats() for link in links]
        gs0 = len(gs_delays)
        t0 = time.monotonic()
        time.sleep(duration)
        elapsed = time.monotonic() - t0
        lat1, pk1 = sim.report()
        s1 = [link.stats() for link in links]
        active.clear()
        for link, cb in zip(links, callbacks):
            link.remove_telemetry_callback(cb)
        lat = np.array(lat1[len(lat0):]) * 1e3
        gs = np.array(gs_delays[gs0:]) * 1e3
        up = np.array([(b.packets_sent - a.packets_sent) / elapsed for a, b in zip(s0, s1)])
        down = np.array([(b.packets_received - a.packets_received) / elapsed for a, b in zip(s0, s1)])
        tel = np.array([(b.telemetry_received - a.telemetry_received) / elapsed for a, b in zip(s0, s1)])
        sim_rx = np.array([(b[0] - a[0]) / elapsed for a, b in zip(pk0, pk1)])
        sim_tx = np.array([(b[1] - a[1]) / elapsed for a, b in zip(pk0, pk1)])
        transactions = np.maximum(up, down)  # each radio transaction carries one packet each way at most
        expected = n * duration * 1000.0 / period_ms / every
        return {
            "drones": n, "period_ms": period_ms, "setpoint_hz": setpoint_hz, "duration_s": round(elapsed, 2),
            "sim": "in-process" if sim_in_process else "own process",
            "samples": int(lat.size), "samples_expected": int(expected),
            "latency_ms": {"p50": _pct(lat, 50), "p90": _pct(lat, 90), "p99": _pct(lat, 99),
                           "max": float(lat.max()) if lat.size else None,
                           "mean": float(lat.mean()) if lat.size else None},
            "gs_callback_to_sent_ms": {"p50": _pct(gs, 50), "p99": _pct(gs, 99)},
            "per_link_packets_per_s": {"up_mean": float(up.mean()), "down_mean": float(down.mean()),
                                       "telemetry_mean": float(tel.mean()),
                                       "sim_rx_mean": float(sim_rx.mean()), "sim_tx_mean": float(sim_tx.mean())},
            "radio_transactions_per_s": {"per_link_mean": float(transactions.mean()),
                                         "all_links": float(transactions.sum()),
                                         "budget_one_radio_estimate": RADIO_TRANSACTIONS_PER_S},
            "p99_target_ms": P99_TARGET_MS,
            "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                        "load_avg_1m_at_end": os.getloadavg()[0]},
        }
    finally:
        for link in links:  # before the simulator goes: cflib reports a vanished UDP peer as a link error
            link.close()
        sim.stop()


def _pct(a: np.ndarray, q: float) -> float | None:
    return float(np.percentile(a, q)) if a.size else None


@pytest.mark.slow
@pytest.mark.parametrize("sim_in_process", [False, True], ids=["sim-own-process", "sim-in-process"])
def test_twelve_drones_measurement_to_setpoint_latency(sim_in_process):
    pytest.importorskip("cflib")
    res = measure(12, period_ms=20, setpoint_hz=50.0, duration=10.0, sim_in_process=sim_in_process)
    print(json.dumps(res, indent=1))
    # Every setpoint answered a measurement, and nearly every measurement got its setpoint.
    assert res["samples"] >= 0.9 * res["samples_expected"], res
    lat = res["latency_ms"]
    assert lat["p50"] < lat["p99"] <= lat["max"]
    if not sim_in_process:
        # The target applies to the ground station's path. With the simulator in the same interpreter its own
        # wait for the GIL (to read the setpoint off its socket) is counted too, which no drone has.
        assert lat["p99"] <= P99_TARGET_MS, f"p99 {lat['p99']:.2f} ms > {P99_TARGET_MS} ms (load {os.getloadavg()})"
    assert res["per_link_packets_per_s"]["telemetry_mean"] >= 0.9 * 1000 / 20  # every link kept its 50 Hz


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drones", type=int, default=12)
    ap.add_argument("--period-ms", type=int, default=20)
    ap.add_argument("--setpoint-hz", type=float, default=50.0)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--sim-in-process", action="store_true")
    a = ap.parse_args()
    print(json.dumps(measure(a.drones, a.period_ms, a.setpoint_hz, a.duration, a.sim_in_process), indent=1))
