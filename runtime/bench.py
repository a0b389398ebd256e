"""``swarm-runtime bench``: time one drone's actor on this machine, the way its control loop calls it.

Single-observation inference through every engine, interleaved in blocks so that a load spike hits all of
them alike: the compiled engine and tuned onnxruntime (``runtime.policy.OnnxPolicy.act`` with the checks), and
onnxruntime with its default options and ``session.run`` (what a first attempt writes). Then the call after a
control period idle (caches gone cold), with and without ``warm()`` just before it. Optionally the whole swarm
at a control rate (``--loop-seconds``), once per engine, through ``runtime.swarm.run_swarm``.

Torch-free, like the rest of ``runtime``: the torch eager comparison lives in
``tests/benchmarks/test_bench_runtime.py``.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

ENGINE_ROWS = ("compiled", "onnxruntime tuned", "onnxruntime default")


def call_times_us(f, obs: np.ndarray, n: int) -> np.ndarray:
    """Wall time [us] of each of ``n`` calls ``f(obs[k % len(obs)])``."""
    t = np.empty(n)
    pc = time.perf_counter_ns
    m = len(obs)
    for k in range(n):
        o = obs[k % m]
        t0 = pc()
        f(o)
        t[k] = pc() - t0
    return t / 1e3


def cold_calls_us(pol, obs: np.ndarray, n: int, idle_s: float = 0.01) -> tuple[list[float], list[float]]:
    """``n`` calls of ``pol.act`` after ``idle_s`` idle each (caches gone cold), and ``n`` more with
    ``pol.warm()`` just before the call, interleaved: their times [us], (cold, after warm-up)."""
    out = np.zeros(pol.act_dim, dtype=np.float32)
    cold, warmed = [], []
    for k in range(2 * n):
        time.sleep(idle_s)
        if k % 2:
            pol.warm()
        t0 = time.perf_counter_ns()
        pol.act(obs[k % len(obs)], out=out)
        (warmed if k % 2 else cold).append((time.perf_counter_ns() - t0) / 1e3)
    return cold, warmed


def bench_inference(models: str | Path, agent: int = 0, calls: int = 20000, blocks: int = 5,
                    idle_s: float = 0.01, cold_calls: int = 40) -> dict:
    """Per-call latency [us] of agent ``agent``'s actor in each engine: p50, p99, min; and the cold call."""
    import onnxruntime as ort

    from runtime.policy import INPUT_NAME, OnnxPolicy, read_manifest, session_options
    from runtime.spec import SpecError
    man = read_manifest(models)
    if not 0 <= agent < len(man.agents):
        raise SpecError(f"--agent: {agent} is not an agent index of {models} (0..{len(man.agents) - 1})")
    e = man.agents[agent]
    pols = {"compiled": OnnxPolicy(e.file, spec=man.spec, role=e.role, sha256=e.sha256, engine="compiled"),
            "onnxruntime tuned": OnnxPolicy(e.file, spec=man.spec, role=e.role, sha256=e.sha256)}
    plain = ort.InferenceSession(str(e.file), session_options(tuned=False), providers=["CPUExecutionProvider"])
    lo, hi = man.spec.layout(e.role).bounds()
    obs = np.random.default_rng(0).uniform(lo, hi, (512, len(lo)))
    out = {k: np.zeros(2, dtype=np.float32) for k in pols}
    calls_by = {name: (lambda o, p=p, y=out[name]: p.act(o, out=y)) for name, p in pols.items()}
    calls_by["onnxruntime default"] = lambda o: plain.run(None, {INPUT_NAME: o[None].astype(np.float32)})
    parts: dict[str, list[np.ndarray]] = {k: [] for k in calls_by}
    per_block = max(1, calls // blocks)
    for _ in range(blocks):
        for name, f in calls_by.items():
            for o in obs[:50]:
                f(o)
            parts[name].append(call_times_us(f, obs, per_block))
    res: dict = {"agent": e.id, "role": e.role.label, "obs_dim": int(len(lo)), "calls_per_engine": per_block * blocks,
                 "load_avg_1min": round(os.getloadavg()[0], 2), "engines": {}}
    for name, ts in parts.items():
        t = np.concatenate(ts)
        res["engines"][name] = {"p50_us": float(np.percentile(t, 50)), "p99_us": float(np.percentile(t, 99)),
                                "min_us": float(t.min())}
    for name, pol in pols.items():
        cold, warmed = cold_calls_us(pol, obs, cold_calls, idle_s)
        res["engines"][name]["cold_p50_us"] = float(np.median(cold))
        res["engines"][name]["after_warm_p50_us"] = float(np.median(warmed))
    res["engines"]["compiled"]["parity_vs_onnxruntime"] = pols["compiled"].compiled_parity
    return res


def format_inference(res: dict, idle_s: float) -> str:
    lines = [f"{res['agent']} ({res['role']}, {res['obs_dim']} inputs), {res['calls_per_engine']} calls per engine in "
             f"interleaved blocks, load average {res['load_avg_1min']}", "",
             f"  {'engine':<22}{'p50 [us]':>10}{'p99 [us]':>10}{'min [us]':>10}"
             f"{f'cold after {idle_s * 1e3:g} ms':>22}{'after warm()':>14}"]
    base = res["engines"]["onnxruntime default"]["p50_us"]
    for name in ENGINE_ROWS:
        r = res["engines"][name]
        cold = f"{r['cold_p50_us']:.1f}" if "cold_p50_us" in r else "-"
        warm = f"{r['after_warm_p50_us']:.1f}" if "after_warm_p50_us" in r else "-"
        lines.append(f"  {name:<22}{r['p50_us']:>10.1f}{r['p99_us']:>10.1f}{r['min_us']:>10.1f}{cold:>22}{warm:>14}"
                     f"   {base / r['p50_us']:.1f}x vs default")
    lines.append(f"\n  compiled vs onnxruntime, max |difference| at load: "
                 f"{res['engines']['compiled']['parity_vs_onnxruntime']:.2g}")
    return "\n".join(lines)


def bench_loop(models: str | Path, seconds: float, rate_hz: float, engine: str) -> dict:
    from runtime.swarm import RunConfig, run_swarm
    r = run_swarm(models, RunConfig(duration_s=seconds, rate_hz=rate_hz, engine=engine))
    keys = ("agent_ticks", "tick_to_action_p50_us", "tick_to_action_p99_us", "tick_to_action_max_us",
            "deadline_misses", "skipped_ticks", "agent_faults", "rss_mib")
    return {k: r.get(k) for k in keys} | {"engine": engine, "rate_hz": rate_hz, "seconds": seconds,
                                          "agents": r["config"]["agents"]}


def cmd_bench(args: argparse.Namespace) -> int:
    from runtime.cli import check_run_length
    if args.loop_seconds > 0:
        check_run_length("--loop-seconds", args.loop_seconds, args.rate, args.models)
    res = bench_inference(args.models, args.agent, args.calls, idle_s=args.idle)
    print(format_inference(res, args.idle), flush=True)
    res["loops"] = []
    if args.loop_seconds > 0:
        print(f"\n  the swarm at {args.rate:g} Hz for {args.loop_seconds:g} s, threads over the in-process bus:")
        for engine in ("compiled", "onnxruntime"):
            r = bench_loop(args.models, args.loop_seconds, args.rate, engine)
            res["loops"].append(r)
            print(f"  {engine:<12} {r['agents']} agents, {r['agent_ticks']} ticks: tick-to-action p50 "
                  f"{r['tick_to_action_p50_us']:.0f} us, p99 {r['tick_to_action_p99_us']:.0f} us, max "
                  f"{r['tick_to_action_max_us']:.0f} us; deadline misses {r['deadline_misses']}", flush=True)
    if args.json is not None:
        from runtime.cli import write_json
        write_json(args.json, res)
        print(f"wrote {args.json}")
    return 0


def add_bench(sub: argparse._SubParsersAction) -> None:
    from runtime.cli import control_rate
    from runtime.cliutil import float_in, int_in, models_dir, nonneg_float, nonneg_int, out_file
    # an idle above a minute is a typo (and time.sleep(inf) overflows)
    idle = float_in(0.0, 60.0, low_open=True, unit="seconds")
    p = sub.add_parser("bench", help="time the actors on this machine (every engine, hot and cold, and the loop)",
                       description=__doc__.split("\n\n")[1].replace("\n", " ").replace("``", ""))
    p.add_argument("--models", required=True, type=models_dir, help="models folder written by `swarm-export onnx`")
    p.add_argument("--agent", type=nonneg_int, default=0, help="index of the agent whose actor is timed (default 0)")
    # fewer than 100 give no p99; the times of every call are kept (8 bytes each)
    p.add_argument("--calls", type=int_in(100, 10_000_000, "calls per engine"), default=20000,
                   help="calls per engine (default 20000)")
    p.add_argument("--idle", type=idle, default=0.01,
                   help="idle time before each cold call [s] (default 0.01, one period at 100 Hz)")
    p.add_argument("--loop-seconds", type=nonneg_float, default=0.0,
                   help="also run the whole swarm this long per engine (0: skip; 10 is a good measurement)")
    p.add_argument("--rate", type=control_rate, default=100.0, help="control rate of the loop run [Hz] (default 100)")
    p.add_argument("--json", type=out_file, default=None, help="also write the figures to this JSON file")
    p.set_defaults(func=cmd_bench)
