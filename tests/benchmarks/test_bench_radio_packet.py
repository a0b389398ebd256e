"""What the radio's fixed-point packet costs the team: ``swarm-runtime run`` with the 60-byte packet only (the
default: int16 positions and velocities, whole-ms times, as on the Crazyflies) against the packet plus the
sender's exact float64 values (``--exact-values``: observations bit-identical to training's), side by side in one
run (runs alternate so that both see the same machine), the shipped models, loss 0, latency 0.

Run (slow, not in the default suite):
    .venv/bin/python -m pytest -q -s -m slow tests/benchmarks/test_bench_radio_packet.py
or standalone, writing results/radio_packet_cost.md and .json:
    .venv/bin/python tests/benchmarks/test_bench_radio_packet.py --runs 4 --duration 20
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
KEYS = (("mean_min_dist", "min dist [m]", "{:.3f}"), ("mean_avg_dist", "mean dist [m]", "{:.3f}"),
        ("tracking_rate", "tracking", "{:.3f}"), ("coverage", "coverage", "{:.3f}"),
        ("collisions_per_episode", "collisions/ep", "{:.2f}"), ("captures_per_episode", "captures/ep", "{:.2f}"))


def measure(runs: int, duration: float, models: Path = ROOT / "models" / "role_based", seed: int = 0) -> dict:
    from runtime.comms import CommConfig
    from runtime.swarm import RunConfig, run_swarm
    out: dict = {"packet": [], "exact": []}
    load = [os.getloadavg()[0]]
    t0 = time.time()
    for _ in range(runs):
        for arm, exact in (("packet", False), ("exact", True)):
            res = run_swarm(models, RunConfig(duration_s=duration, comms=CommConfig(exact_values=exact, seed=seed),
                                              seed=seed))
            out[arm].append({k: res[k] for k, _, _ in KEYS} | {"episodes": res["episodes"],
                                                                "waiting_ticks": res["waiting_ticks"],
                                                                "delivered": res["comms"]["delivered"]})
    load.append(os.getloadavg()[0])
    out["meta"] = {"runs": runs, "duration_s": duration, "models": str(models.relative_to(ROOT)), "seed": seed,
                   "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(t0)),
                   "machine": f"{platform.machine()}, {os.cpu_count()} CPUs", "load_1min_start_end": load,
                   "wall_s": round(time.time() - t0, 1)}
    return out


def markdown(res: dict) -> str:
    m = res["meta"]
    lines = ["# What the radio's fixed-point packet costs the team", "",
             f"`python tests/benchmarks/test_bench_radio_packet.py --runs {m['runs']} --duration {m['duration_s']:g}` "
             f"({m['date']}, {m['machine']}, load average {m['load_1min_start_end'][0]:.1f} at the start and "
             f"{m['load_1min_start_end'][1]:.1f} at the end: trainings ran beside it). `swarm-runtime run` of "
             f"`{m['models']}` (12 agents on threads, 10 Hz, full observability, loss 0, latency 0, world seed "
             f"{m['seed']}), {m['runs']} runs of {m['duration_s']:g} s per arm, alternating: the 60-byte packet alone "
             "(the default) against the packet with the exact float64 values beside it (`--exact-values`).", "",
             "| metric | packet (runs) | packet median | exact (runs) | exact median |", "|---|---|---|---|---|"]
    for key, label, fmt in KEYS:
        p = [r[key] for r in res["packet"]]
        e = [r[key] for r in res["exact"]]
        lines.append(f"| {label} | {', '.join(fmt.format(v) for v in p)} | {fmt.format(float(np.median(p)))} | "
                     f"{', '.join(fmt.format(v) for v in e)} | {fmt.format(float(np.median(e)))} |")
    lines += ["", "Ticks the agents spent waiting to hear their whole team, per run: packet "
              f"{[r['waiting_ticks'] for r in res['packet']]}, exact {[r['waiting_ticks'] for r in res['exact']]} "
              "(10 pursuer-team agents wait one tick at the start of each episode: 20 in a 2-episode run; more when "
              "a teammate's first message of an episode came a tick late).", "",
              _reading(res), ""]
    return "\n".join(lines)


def _reading(res: dict) -> str:
    """Which metrics' medians differ by more than the runs of either arm spread (the noise of real-time runs)."""
    beyond = []
    for key, label, fmt in KEYS:
        p, e = [r[key] for r in res["packet"]], [r[key] for r in res["exact"]]
        spread = max(max(p) - min(p), max(e) - min(e))
        if abs(float(np.median(p)) - float(np.median(e))) > spread:
            beyond.append(f"{label} ({fmt.format(float(np.median(p)))} vs {fmt.format(float(np.median(e)))})")
    if not beyond:
        return ("Reading: every median differs between the arms by less than the runs of one arm spread: at this "
                "length the fixed-point packet costs the team nothing measurable.")
    return "Reading: beyond the run-to-run spread: " + ", ".join(beyond) + "."


@pytest.mark.slow
def test_both_radio_arms_fly_full_episodes_and_hear_their_team():
    res = measure(2, 20.0)
    for arm in ("packet", "exact"):
        assert all(r["episodes"] >= 2 and r["delivered"] > 0 for r in res[arm])
    print(markdown(res))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "radio_packet_cost")
    a = ap.parse_args()
    r = measure(a.runs, a.duration)
    from runtime.cliutil import write_json_atomic, write_text_atomic
    write_json_atomic(a.out.with_suffix(".json"), r)
    write_text_atomic(a.out.with_suffix(".md"), markdown(r))
    print(markdown(r))
