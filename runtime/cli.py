"""``swarm-runtime``: run the per-drone runtimes against the simulated world, in real time.

``run``      every agent of a models folder on its own thread (or process) against one env; prints the paper's
             metrics and the loop timing, optionally writes them as JSON.
``degrade``  ``run`` over a grid of message loss x latency; writes a metrics table (Markdown and JSON).
``bench``    time one actor on this machine in every engine (hot, cold, after warm-up) and optionally the
             whole swarm's loop per engine.

A bad models folder (or any input error) prints the named error with its fix and exits 2, never a traceback.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import platform
import sys
import time
from pathlib import Path

from runtime.cliutil import (ArgumentParser, float_in, EXIT_USAGE, float_list, int_in, json_safe, models_dir,
                             nonneg_float, out_file, out_prefix, positive_float, probability, seed,
                             write_json_atomic, write_text_atomic)
from runtime.comms import CommConfig
from runtime.spec import ENGINES, SpecError

JSON_KEYS = ("mean_min_dist", "mean_avg_dist", "mean_max_dist", "tracking_rate", "coverage", "collisions_per_episode",
             "episodes", "tick_to_action_p50_us", "tick_to_action_p99_us", "deadline_misses", "steps")
"""Keys every ``run --json`` file has (the evaluator's metric keys plus the loop timing)."""

_METRIC_LABELS = (("episodes", "episodes"), ("mean_min_dist", "min pursuer-target distance [m]"),
                  ("mean_avg_dist", "mean pursuer-target distance [m]"),
                  ("mean_max_dist", "max pursuer-target distance [m]"),
                  ("tracking_rate", "tracking rate (target within sensing range)"),
                  ("coverage", "coverage (episode)"), ("collisions_per_episode", "collisions / episode"),
                  ("captures_per_episode", "captures / episode"))


_probability = probability
_nonneg = nonneg_float
_positive = positive_float
_floats = float_list(nonneg_float, "numbers >= 0", "0,0.2,0.5")

MAX_RATE_HZ = 1000.0
"""The fastest control rate a run takes: the world and every agent step in Python, which keeps up with a few
hundred Hz at best; a faster --rate is a typo."""
control_rate = float_in(0.0, MAX_RATE_HZ, low_open=True, unit="Hz")

MAX_TICKS = 1_000_000
"""Control ticks per agent a run may last: every tick's timing is recorded (arrays sized before the run)."""


def check_run_length(option: str, seconds: float, rate_hz: float | None, models) -> None:
    """``seconds`` at ``rate_hz`` (None: the models' spec control rate) is at least one control tick and at most
    ``MAX_TICKS``; else ``SpecError`` naming ``option`` (before any agent starts)."""
    if rate_hz is None:
        from runtime.policy import read_manifest
        rate_hz = 1.0 / read_manifest(models).spec.timing.control_period
    ticks = seconds * rate_hz
    if ticks < 1:
        raise SpecError(f"{option} {seconds:g} s at {rate_hz:g} Hz is less than one control tick: give "
                        f"{option} >= {1 / rate_hz:g} or a higher --rate")
    if ticks > MAX_TICKS:
        raise SpecError(f"{option} {seconds:g} s at {rate_hz:g} Hz is {ticks:.3g} control ticks; a run records "
                        f"every tick: give {option} <= {MAX_TICKS / rate_hz:g} (at most {MAX_TICKS} ticks)")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", required=True, type=models_dir,
                   help="models folder written by `swarm-export onnx` (manifest.json + one ONNX actor per agent)")
    p.add_argument("--rate", type=control_rate, default=None,
                   help="agents' control rate [Hz] (default: 1 / spec control period; the world steps at that)")
    p.add_argument("--processes", action="store_true",
                   help="each agent in its own process, messages over UDP on loopback (default: threads)")
    p.add_argument("--bandwidth", type=float_in(0.0, low_open=True, allow_inf=True), default=math.inf, help="each sender's channel rate [bit/s]")
    p.add_argument("--comm-range", type=_positive, default=None,
                   help="radio range [m] (default: the spec's comm_range with partial observability, unlimited "
                        "with full)")
    p.add_argument("--jitter", type=_nonneg, default=0.0, help="extra uniform message delay up to this [s]")
    p.add_argument("--exact-values", action="store_true",
                   help="carry the sender's float64 values beside the 60-byte packet, so that observations are "
                        "bit-identical to training's (default: only the packet, int16 fixed point, as on the drones)")
    p.add_argument("--seed", type=seed, default=0, help="world and channel seed")
    p.add_argument("--no-stagger", action="store_true", help="all agents tick at the same instant")
    p.add_argument("--no-warm", action="store_true", help="no warm-up inference before the tick")
    p.add_argument("--no-reuse", action="store_true",
                   help="with --training-encoder: rebuild the observation every tick even when its inputs did not "
                        "change")
    p.add_argument("--training-encoder", action="store_true",
                   help="build observations with the batched training encoder at B = 1 (the reference, ~0.4 ms) "
                        "instead of its bit-identical one-observer numba twin")
    p.add_argument("--engine", choices=ENGINES, default="onnxruntime",
                   help="how each actor runs: onnxruntime (default), or the actor's Gemm/ReLU/tanh chain read from "
                        "the same ONNX file and compiled with numba, checked against onnxruntime at load")


def _run_config(args: argparse.Namespace, duration: float, loss: float, latency: float):
    from runtime.swarm import RunConfig
    comms = CommConfig(latency_s=latency, jitter_s=args.jitter, loss=loss, bandwidth_bps=args.bandwidth,
                       comm_range=args.comm_range, seed=args.seed, exact_values=args.exact_values)
    return RunConfig(duration_s=duration, rate_hz=args.rate, comms=comms, processes=args.processes, seed=args.seed,
                     stagger=not args.no_stagger, warm=not args.no_warm, reuse_observation=not args.no_reuse,
                     fast_encoder=not args.training_encoder, engine=args.engine)


def format_run(res: dict) -> str:
    c = res["config"]
    lines = [f"{c['agents']} agents ({'processes, UDP' if c['processes'] else 'threads, in-process bus'}) at "
             f"{c['rate_hz']:g} Hz for {c['duration_s']:g} s; loss {c['loss']:g}, latency {c['latency_s'] * 1e3:g} ms, "
             f"{_radio(c['exact_values'])}, spec {c['spec_hash']} ({c['observability']} observability)", ""]
    w = max(len(label) for _, label in _METRIC_LABELS)
    for key, label in _METRIC_LABELS:
        v = res.get(key)
        if v is not None:
            lines.append(f"  {label.ljust(w)}  {v if isinstance(v, int) else f'{v:.4f}'}")
    lines += ["", f"  world steps {res['steps']} (late by p99 {res['world_step_late_p99_ms']:.1f} ms), agent ticks "
                  f"{res['agent_ticks']}",
              f"  tick-to-action  p50 {res['tick_to_action_p50_us']:.0f} us  p99 {res['tick_to_action_p99_us']:.0f} us  "
              f"max {res['tick_to_action_max_us']:.0f} us",
              f"  state-to-action p50 {res['state_to_action_p50_us']:.0f} us  p99 {res['state_to_action_p99_us']:.0f} us"
              f"  max {res['state_to_action_max_us']:.0f} us",
              f"  deadline misses {res['deadline_misses']} (skipped ticks {res['skipped_ticks']}), "
              f"faults {res['agent_faults']}, waiting for neighbours {res['waiting_ticks']} ticks, observation "
              f"unchanged (encoder skipped) {res['reused_observations']} ticks",
              "  messages " + ", ".join(f"{k} {v}" for k, v in res["comms"].items() if v)]
    if res.get("agents_cpu_s") is not None:
        lines.append(f"  agents' CPU time {res['agents_cpu_s']} s; host load average {res['host_load_avg_1min'][0]} at "
                     f"start, {res['host_load_avg_1min'][1]} at the end")
    if res.get("rss_mib"):
        lines.append(f"  resident memory {res['rss_mib']} MiB" + (" (sum over agent processes)" if c["processes"]
                                                                  else " (the agents' process)"))
    for agent, fault in res.get("faults_by_agent", {}).items():
        lines.append(f"  fault in {agent}: {fault}")
    return "\n".join(lines)


def _radio(exact_values: bool) -> str:
    return ("radio: the 60-byte packet + exact float64 values (--exact-values)" if exact_values
            else "radio: the 60-byte packet (int16 fixed point)")


_json_safe = json_safe


def write_json(path: Path, obj) -> None:
    """``obj`` as indented JSON at ``path``, atomically (its folder created); NaN -> null, inf -> "inf"."""
    write_json_atomic(path, obj)


def _cmd_run(args: argparse.Namespace) -> int:
    from runtime.swarm import run_swarm
    check_run_length("--duration", args.duration, args.rate, args.models)
    res = run_swarm(args.models, _run_config(args, args.duration, args.loss, args.latency))
    print(format_run(res))
    if args.json is not None:
        write_json(args.json, res)
        print(f"wrote {args.json}")
    return 0


def add_run(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run every agent against the simulated world in real time",
                       description="Every agent of a models folder on its own thread (or process) against one env "
                                   "of runtime.world in real time; prints the paper's metrics and the loop timing.")
    _common(p)
    p.add_argument("--duration", type=_positive, default=30.0, help="seconds of real time")
    p.add_argument("--loss", type=_probability, default=0.0, help="message loss probability")
    p.add_argument("--latency", type=_nonneg, default=0.0, help="message latency [s]")
    p.add_argument("--json", type=out_file, default=None, help="also write the results to this JSON file")
    p.set_defaults(func=_cmd_run)


DEGRADE_COLUMNS = (("tracking_rate", "tracking", "{:.3f}"), ("mean_min_dist", "min dist [m]", "{:.3f}"),
                   ("mean_avg_dist", "mean dist [m]", "{:.3f}"), ("coverage", "coverage", "{:.3f}"),
                   ("collisions_per_episode", "collisions/ep", "{:.2f}"), ("episodes", "episodes", "{}"),
                   ("delivered_fraction", "delivered", "{:.3f}"), ("tick_to_action_p99_us", "tick-to-action p99 [us]", "{:.0f}"),
                   ("deadline_misses", "misses", "{}"))


def _cmd_degrade(args: argparse.Namespace) -> int:
    from runtime.swarm import run_swarm
    check_run_length("--duration", args.duration, args.rate, args.models)
    rows, repeats = [], []
    t0 = time.time()
    cells = [(loss, latency) for latency in args.latencies for loss in args.losses]
    cells += [cells[0]] * args.baseline_repeats
    for k, (loss, latency) in enumerate(cells):
        res = run_swarm(args.models, _run_config(args, args.duration, loss, latency))
        c = res["comms"]
        heard = c["delivered"] + c["dropped_loss"] + c["dropped_range"]
        res["delivered_fraction"] = c["delivered"] / heard if heard else float("nan")
        (rows if k < len(cells) - args.baseline_repeats else repeats).append({"loss": loss, "latency_s": latency,
                                                                             **res})
        print(f"loss {loss:g} latency {latency * 1e3:g} ms: tracking {res['tracking_rate']:.3f}, min dist "
              f"{res['mean_min_dist']:.3f} m, p99 {res['tick_to_action_p99_us']:.0f} us", flush=True)
    out = args.out
    meta = {"models": str(args.models), "duration_s_per_cell": args.duration, "seed": args.seed,
            "rate_hz": rows[0]["config"]["rate_hz"], "processes": args.processes, "exact_values": args.exact_values,
            "spec_hash": rows[0]["config"]["spec_hash"], "observability": rows[0]["config"]["observability"],
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(t0)), "machine": _machine(),
            "wall_s": round(time.time() - t0, 1)}
    write_json(out.with_suffix(".json"), {"meta": meta, "rows": rows, "baseline_repeats": repeats})
    write_text_atomic(out.with_suffix(".md"), degradation_markdown(meta, rows, repeats))
    print(f"wrote {out.with_suffix('.md')} and {out.with_suffix('.json')}")
    return 0


def _machine() -> str:
    import os
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} CPUs, {platform.system()} {platform.release()}"


def degradation_markdown(meta: dict, rows: list[dict], repeats: list[dict] | None = None) -> str:
    head = "| loss | latency [ms] | " + " | ".join(c[1] for c in DEGRADE_COLUMNS) + " |"
    sep = "|" + "---|" * (2 + len(DEGRADE_COLUMNS))
    lines = [f"# Runtime degradation: message loss x latency", "",
             f"`swarm-runtime degrade --models {meta['models']} --duration {meta['duration_s_per_cell']:g}"
             f"{' --exact-values' if meta.get('exact_values') else ''}` "
             f"({meta['date']}, {meta['machine']}); {_radio(meta.get('exact_values', False))}; {meta['rate_hz']:g} Hz "
             f"agents, "
             f"{'processes over UDP' if meta['processes'] else 'threads over the in-process bus'}, spec "
             f"{meta['spec_hash']} ({meta['observability']} observability), world seed {meta['seed']} in every "
             f"cell (same episodes; differences come from the channel and from thread timing).", "",
             _what_comms_carry(meta["observability"]), "", head, sep]
    for r in rows:
        cells = []
        for key, _, fmt in DEGRADE_COLUMNS:
            v = r.get(key)
            cells.append("-" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v))
        lines.append(f"| {r['loss']:g} | {r['latency_s'] * 1e3:g} | " + " | ".join(cells) + " |")
    if repeats:
        base = [rows[0]] + list(repeats)
        lines += ["", f"Run-to-run spread: the first cell (loss {rows[0]['loss']:g}, latency "
                      f"{rows[0]['latency_s'] * 1e3:g} ms) run {len(base)} times gives"]
        for key, label, fmt in DEGRADE_COLUMNS[:5]:
            vals = [r[key] for r in base]
            lines.append(f"- {label}: " + ", ".join(fmt.format(v) for v in vals)
                         + f" (range {fmt.format(max(vals) - min(vals))})")
        lines.append("Differences between cells smaller than these ranges are within the noise of real-time runs.")
    lines.append("")
    return "\n".join(lines)


def _what_comms_carry(observability: str) -> str:
    if observability == "full":
        return ("With full observability (what the paper trained with) every drone senses every target itself and "
                "the radio is unlimited in range; loss and latency act on what it knows of its teammates (their "
                "positions and velocities in the observation's teammate slots are as old as the last message heard).")
    return ("With partial observability targets are known only by own sensing or relayed sightings, and teammates "
            "only within comm range: loss and latency act on both the teammate slots and the target slots (ages).")


def add_degrade(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("degrade", help="run over message loss x latency and write the metrics table",
                       description="`run` for every (loss, latency) pair; writes OUT.md and OUT.json.")
    _common(p)
    p.add_argument("--duration", type=_positive, default=30.0, help="seconds of real time per cell")
    p.add_argument("--losses", type=float_list(probability, "probabilities in [0, 1]", "0,0.2,0.5"), default=[0.0, 0.2, 0.5], help="comma-separated loss probabilities")
    p.add_argument("--latencies", type=float_list(nonneg_float, "latencies >= 0 [s]", "0,0.05,0.2"), default=[0.0, 0.05, 0.2], help="comma-separated latencies [s]")
    p.add_argument("--baseline-repeats", type=int_in(0, 100), default=0,
                   help="run the first cell this many extra times to show the run-to-run spread")
    p.add_argument("--out", type=out_prefix(".md", ".json"), default=Path("results/runtime_degradation"),
                   help="output path without suffix (writes .md and .json)")
    p.set_defaults(func=_cmd_degrade)


def add_bench(sub: argparse._SubParsersAction) -> None:
    from runtime.bench import add_bench as add
    add(sub)


SUBCOMMANDS = [add_run, add_degrade, add_bench]


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="swarm-runtime", description=__doc__.splitlines()[0].replace("``", ""))
    parser.add_argument("-v", "--verbose", action="store_true", help="log faults and progress")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in SUBCOMMANDS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.ERROR, format="%(message)s")
    from runtime.policy import PolicyError
    try:
        return args.func(args)
    except PolicyError as exc:  # every one is about the models folder
        print(f"swarm-runtime {args.command}: error: --models: {type(exc).__name__}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except SpecError as exc:
        print(f"swarm-runtime {args.command}: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (RuntimeError, OSError) as exc:
        print(f"swarm-runtime {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"swarm-runtime {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
