"""``swarm-gs``: the ground station's command line.

Each subcommand registers itself in one function ``_add_<name>(subparsers)`` that sets ``func``; add a
subcommand by writing one such function and listing it in ``SUBCOMMANDS``.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import socket
import sys
import threading
import time
from pathlib import Path

from groundstation.cli_common import (UsageError, add_no_separation, add_view, check_actor_files, check_fence_arena,
                                      check_port_range, opt_str, read_input)
from groundstation.cli_fleet import _add_fly, _add_land, _add_status
from groundstation.sim.swarm import DEFAULT_BASE_PORT, SimError, SimSwarm
from runtime.cliutil import (EXIT_USAGE, ArgumentParser, int_in, models_dir, nonneg_int, out_file,
                             out_picture, port, positive_float, seed)
from runtime.spec import ENGINES, SpecError


def _add_sim(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "sim", help="run simulated Crazyflies (CRTP over UDP) for any cflib client",
        description="Start N simulated Crazyflies on UDP ports base-port+i. Connect with cflib as "
                    "udp://HOST:PORT, e.g. SyncCrazyflie('udp://127.0.0.1:19850'). Ctrl-C stops them.")
    p.add_argument("--drones", type=nonneg_int, default=1, help="number of drones (default 1)")
    p.add_argument("--base-port", type=port, default=DEFAULT_BASE_PORT,
                   help=f"UDP port of drone 0 (default {DEFAULT_BASE_PORT}, where cflib scans)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the positioning noise (default 0)")
    p.add_argument("--spacing", type=positive_float, default=0.5, help="distance between start positions [m]")
    p.add_argument("--duration", type=positive_float, default=None,
                   help="stop after this many seconds (default: run until Ctrl-C)")
    p.add_argument("--mavlink", type=nonneg_int, default=0, metavar="M",
                   help="also run M simulated MAVLink vehicles (system ids 1..M) that send to a ground station "
                        "listening on --mavlink-port+i; connect with mavlink:udpin:HOST:PORT (default 0)")
    p.add_argument("--mavlink-port", type=port, default=14550,
                   help="UDP port the ground station listens on for vehicle 1 (default 14550)")
    p.add_argument("--autopilot", choices=("ardupilot", "px4"), default="ardupilot",
                   help="what the MAVLink vehicles behave as: 'ardupilot' (ArduCopter: GUIDED, LAND, RTL, LOITER "
                        "custom modes) or 'px4' (PX4's mode encoding, OFFBOARD only after a setpoint stream) "
                        "(default ardupilot)")
    p.set_defaults(func=_run_sim)


def _run_sim(args: argparse.Namespace) -> int:
    if args.drones + args.mavlink < 1:
        raise UsageError(f"--drones {args.drones} --mavlink {args.mavlink}: no drone to simulate; give at least one, "
                         f"e.g. --drones 3, or --drones 0 --mavlink 1")
    check_port_range("--base-port", args.base_port, args.drones)
    check_port_range("--mavlink-port", args.mavlink_port, args.mavlink, "--mavlink")
    if args.drones and args.mavlink and (args.base_port < args.mavlink_port + args.mavlink
                                         and args.mavlink_port < args.base_port + args.drones):
        raise UsageError(f"--mavlink-port {args.mavlink_port}: the MAVLink ground station's ports "
                         f"{args.mavlink_port}..{args.mavlink_port + args.mavlink - 1} overlap the simulated "
                         f"Crazyflies' {args.base_port}..{args.base_port + args.drones - 1} (--base-port): give ranges "
                         f"apart, e.g. the defaults")
    try:
        socket.getaddrinfo(args.host, None, type=socket.SOCK_DGRAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise UsageError(f"--host: cannot resolve {args.host!r} ({exc}); give an address such as 127.0.0.1 or "
                         f"0.0.0.0") from None
    sims = None
    vehicles = []
    try:
        if args.drones:
            sims = SimSwarm(args.drones, base_port=args.base_port, host=args.host, seed=args.seed,
                            spacing=args.spacing).start()
        if args.mavlink:
            from groundstation.mavlink_autopilot import Autopilot
            from groundstation.sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig
            for i in range(args.mavlink):
                start = (i * args.spacing, -args.spacing, 0.0)
                config = VehicleConfig(system_id=i + 1, autopilot=Autopilot(args.autopilot))
                vehicles.append(MavlinkVehicle(f"udpout:{args.host}:{args.mavlink_port + i}", config, start=start,
                                               seed=args.seed + i).start())
    except (SimError, OSError) as exc:
        print(f"swarm-gs sim: error: {exc}", file=sys.stderr)
        _stop_sims(sims, vehicles)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if sims is not None:
        print(f"{args.drones} simulated Crazyflies:", flush=True)
        for uri in sims.uris:
            print(f"  {uri}", flush=True)
    if vehicles:
        print(f"{len(vehicles)} simulated MAVLink vehicles:", flush=True)
        for i in range(len(vehicles)):
            print(f"  mavlink:udpin:{args.host}:{args.mavlink_port + i}", flush=True)
    try:
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            stop.wait(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        _stop_sims(sims, vehicles)
    print("simulators stopped", flush=True)
    return 0


def _stop_sims(sims, vehicles) -> None:
    for vehicle in vehicles:
        vehicle.stop()
    if sims is not None:
        sims.stop()


def _kill_link(text: str) -> tuple[str, float]:
    drone, sep, at = text.partition("@")
    try:
        t = float(at)
    except ValueError:
        t = math.nan
    if not sep or not drone or not (t >= 0 and math.isfinite(t)):
        raise argparse.ArgumentTypeError(f"expected DRONE@SECONDS (e.g. 3@10 or cf3@10), got {text!r}")
    return drone, t


def _add_demo(subparsers: argparse._SubParsersAction) -> None:
    from groundstation.demo import DemoOptions
    d = DemoOptions()
    p = subparsers.add_parser(
        "demo", help="fly the whole stack against simulated Crazyflies through cflib (one per agent of --models)",
        description="Start one simulated Crazyflie per agent of the models (12 for models/role_based: 5 pursuers, 5 "
                    "scouts, 2 evaders; 6 for models/paper_flight, the paper's real-drone team, whose flight figure "
                    "is printed beside ours), connect through cflib over "
                    "udp://, assign roles, fly the mission with the exported actors, land, and print the paper's "
                    "metrics and link statistics. Ctrl-C lands everyone.")
    p.add_argument("--duration", type=positive_float, default=d.duration,
                   help=f"mission time [s] (default {d.duration:g})")
    p.add_argument("--speed", type=positive_float, default=d.speed,
                   help="multiplier on the policies' velocity commands (default 1)")
    p.add_argument("--kill-link", type=_kill_link, default=None, metavar="DRONE@T",
                   help="cut drone DRONE's link (index or id, e.g. 3 or cf3) T s into the mission")
    p.add_argument("--loss", type=float, default=d.loss,  # checked in _check_demo (main returns 2)
                   help="probability of losing each datagram (default 0)")
    p.add_argument("--telemetry-period-ms", type=int_in(10, 1000, "ms"), default=d.telemetry_period_ms,
                   metavar="MS", help=f"telemetry period per drone [ms] (default {d.telemetry_period_ms})")
    p.add_argument("--json", type=out_file, default=None, metavar="PATH", help="write the results to this JSON file")
    p.add_argument("--log", type=out_file, default=None, metavar="PATH",
                   help="write the flight log here: MCAP for Foxglove when PATH ends in .mcap, else JSON lines "
                        "(.jsonl)")
    p.add_argument("--plot", type=out_picture, default=None, metavar="PNG",
                   help="draw the trajectories to this picture (.png, .pdf, .svg, ...)")
    add_view(p)
    p.add_argument("--models", default=d.models, help=f"models folder from swarm-export onnx (default {d.models})")
    p.add_argument("--engine", choices=ENGINES, default=d.engine,
                   help="how the actors run: onnxruntime (default) or compiled (the same ONNX actors compiled with "
                        "numba, checked against onnxruntime at load)")
    p.add_argument("--spec", default=d.spec, metavar="TOML",
                   help="experiment TOML whose [spec] the ground station uses (default: the spec the models "
                        "were trained on, from their manifest.json; a different one fails preflight)")
    p.add_argument("--fence", default=d.fence, metavar="TOML", help=f"geofence (default {d.fence}); its "
                   "keep-out circles are replaced by the obstacles drawn for the demo")
    p.add_argument("--anchors", default=d.anchors, metavar="TOML",
                   help=f"LPS anchors (default {d.anchors})")
    p.add_argument("--flight-config", default=None, metavar="TOML",
                   help="TOML with a [flight] table (and optionally a [separation] table)")
    p.add_argument("--seed", type=seed, default=d.seed, help="obstacles, start positions, noise (default 0)")
    p.add_argument("--base-port", type=port, default=None, help="UDP port of drone 0 (default: a free range)")
    add_no_separation(p)
    p.add_argument("--sim-in-process", action="store_true",
                   help="run the simulated Crazyflies in the ground station's interpreter (default: a process of "
                        "their own, as real drones are; in-process they share its GIL), for comparison")
    p.set_defaults(func=_run_demo)


def _check_demo(args: argparse.Namespace) -> None:
    """Every input of ``swarm-gs demo`` read and checked before a simulator starts, so that a wrong value is one
    line naming its option rather than an error after a 30 s flight (``run_demo`` reads them again)."""
    from groundstation.flight import FlightConfig
    from groundstation.positioning import AnchorLayout
    from groundstation.safety import FenceConfig
    from groundstation.separation import SeparationConfig
    from runtime.policy import PolicyError, read_manifest
    from runtime.spec import SwarmSpec, load_toml
    from groundstation.demo import DemoOptions
    defaults = DemoOptions()
    for option, name in (("--models", "models"), ("--fence", "fence"), ("--anchors", "anchors")):
        value = getattr(args, name)
        if value == getattr(defaults, name) and not Path(value).exists():
            raise UsageError(f"{option}: the default {value!r} is relative to the repository root and is not in "
                             f"{os.getcwd()}: run swarm-gs there or give {option} PATH")
    for option, name in (("--spec", "spec"), ("--flight-config", "flight_config")):
        value = getattr(args, name)
        if value is not None and not value.strip():  # "" would read as "not given" and fly the defaults
            raise UsageError(f"{option}: expected a TOML file path, got ''; leave {option} out for the default")
    if not 0.0 <= args.loss < 1.0:
        raise UsageError(f"--loss: expected a probability in [0, 1), got {args.loss:g}")
    if args.kill_link is not None and args.kill_link[1] >= args.duration:
        raise UsageError(f"--kill-link: {args.kill_link[0]}@{args.kill_link[1]:g} is not within the "
                         f"{args.duration:g} s mission (--duration): give a time below {args.duration:g}")
    try:
        manifest = read_manifest(models_dir(args.models))
    except (PolicyError, argparse.ArgumentTypeError) as exc:
        raise UsageError(f"--models: {exc}") from None
    check_actor_files("--models", manifest)
    spec = read_input("--spec", args.spec, SwarmSpec.from_toml, ("spec",)) if args.spec else manifest.spec
    if spec.hash != manifest.spec.hash:  # preflight would refuse it too, after starting every simulator
        raise UsageError(f"--spec {args.spec}: spec {spec.hash}, but the models in {args.models} were exported for "
                         f"spec {manifest.spec.hash}: give the spec they were trained on, or leave --spec out")
    if args.flight_config:
        read_input("--flight-config", args.flight_config, FlightConfig.from_toml, ("flight", "separation"))
        read_input("--flight-config", args.flight_config,
               lambda p: SeparationConfig.from_dict(load_toml(p).get("separation", {})))
    fence = read_input("--fence", args.fence, lambda p: FenceConfig.from_toml(p, spec=manifest.spec), ("fence",))
    check_fence_arena(fence, manifest.spec, f"--fence {args.fence}", f"the models in {args.models}")
    read_input("--anchors", args.anchors, lambda p: AnchorLayout.from_toml(p, fence=fence), ("lps",))
    if args.base_port is not None:
        check_port_range("--base-port", args.base_port, spec.n_agents)
    # the --kill-link drone is resolved by run_demo, also before any simulator starts


def _run_demo(args: argparse.Namespace) -> int:
    from groundstation.demo import DemoError, DemoOptions, format_summary, run_demo
    from groundstation.flight import PreflightError
    from runtime.policy import PolicyError
    _check_demo(args)
    opts = DemoOptions(duration=args.duration, speed=args.speed, kill_link=args.kill_link, loss=args.loss,
                       models=args.models, engine=args.engine, spec=args.spec, fence=args.fence, anchors=args.anchors,
                       flight=args.flight_config, seed=args.seed, json_path=opt_str(args.json),
                       log_path=opt_str(args.log), plot_path=opt_str(args.plot), base_port=args.base_port,
                       telemetry_period_ms=args.telemetry_period_ms, separation=not args.no_separation,
                       sim_in_process=args.sim_in_process, view_port=args.view)
    try:
        res = run_demo(opts, echo=lambda line: print(line, flush=True))
    except (DemoError, PolicyError, SpecError, PreflightError, SimError) as exc:
        print(f"swarm-gs demo: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"swarm-gs demo: interrupted; {exc or 'landing was not confirmed'}", file=sys.stderr)
        return 130
    print(format_summary(res))
    for flag, path in (("json", args.json), ("log", args.log), ("plot", args.plot)):
        if path:
            print(f"wrote {path}")
    return 0


def _add_replay(subparsers: argparse._SubParsersAction) -> None:
    from groundstation.liveview.server import DEFAULT_PORT
    from runtime.cliutil import float_in, in_file
    p = subparsers.add_parser("replay", help="play a flight log (JSON lines or MCAP) into the live page",
                              description="Serve the live page and play LOG (written by --log of demo or fly) into "
                                          "it, with pause, seek and speed on the page. Ctrl-C stops.")
    p.add_argument("log", type=in_file, metavar="LOG", help="flight log: .jsonl or .mcap")
    p.add_argument("--view", type=port, default=DEFAULT_PORT, metavar="PORT",
                   help=f"serve the page on http://127.0.0.1:PORT/ (default {DEFAULT_PORT})")
    p.add_argument("--speed", type=positive_float, default=1.0, help="replay time per wall time (default 1)")
    p.add_argument("--start", type=float_in(0.0, unit="s"), default=0.0, help="start this many s into the log")
    p.add_argument("--once", action="store_true",
                   help="exit when the log has played to its end (default: keep serving until Ctrl-C)")
    p.set_defaults(func=_run_replay)


def _read_log(path) -> list:
    from groundstation.mcap_log import LogError, read_log
    try:
        return read_log(path)
    except LogError as exc:
        raise UsageError(f"LOG: {exc}") from None


def _run_replay(args: argparse.Namespace) -> int:
    from groundstation.liveview import LiveView, ViewError
    from groundstation.mcap_log import LogError
    from groundstation.replay import ReplaySource
    rows = _read_log(args.log)
    try:
        source = ReplaySource(rows, speed=args.speed, start=args.start)
    except LogError as exc:
        raise UsageError(f"LOG {args.log}: {exc}") from None
    if args.start >= source.duration > 0:
        raise UsageError(f"--start {args.start:g}: past the end of LOG {args.log} ({source.duration:.1f} s long); give "
                         f"a time below {source.duration:.1f}")
    try:
        view = LiveView(args.view).start()
    except ViewError as exc:
        raise UsageError(str(exc)) from None
    try:
        view.attach(source)
        print(f"live view: {view.url} (replaying {args.log}, {source.duration:.1f} s, {len(source.ids)} drones; "
              f"Ctrl-C stops)", flush=True)
        while not (args.once and source.finished):
            time.sleep(0.1)
        time.sleep(2.0 / view.rate)  # the last state out to the open pages
    finally:
        view.stop()
    return 0


def _add_report(subparsers: argparse._SubParsersAction) -> None:
    from runtime.cliutil import in_file
    p = subparsers.add_parser("report", help="the paper's metrics and the trajectory picture from a flight log",
                              description="Recompute the paper's metrics (distance to targets, tracking, coverage) "
                                          "from the positions in LOG (.jsonl or .mcap) and draw the trajectories.")
    p.add_argument("log", type=in_file, metavar="LOG", help="flight log: .jsonl or .mcap")
    p.add_argument("--plot", type=out_picture, default=None, metavar="PNG", help="draw the trajectories here")
    p.add_argument("--json", type=out_file, default=None, metavar="PATH", help="write the report as JSON here")
    p.set_defaults(func=_run_report)


def _run_report(args: argparse.Namespace) -> int:
    from groundstation.mcap_log import LogError
    from groundstation.replay import format_report, plot_log, report
    from runtime.cliutil import write_json_atomic
    rows = _read_log(args.log)
    try:
        res = report(rows)
        if args.plot:
            plot_log(str(args.plot), rows)
    except LogError as exc:
        raise UsageError(f"LOG {args.log}: {exc}") from None
    print(format_report(res))
    if args.json:
        write_json_atomic(args.json, res)
    for path in (args.plot, args.json):
        if path:
            print(f"wrote {path}")
    return 0


SUBCOMMANDS = (_add_sim, _add_demo, _add_fly, _add_land, _add_status, _add_replay, _add_report)


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="swarm-gs", description="swarmpursuit ground station")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    subparsers = parser.add_subparsers(dest="command", required=True)
    for add in SUBCOMMANDS:
        add(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not args.verbose:  # cflib logs a missing Crazyradio with its traceback; our LinkError says it in a line
        logging.getLogger("cflib").setLevel(logging.CRITICAL)
    try:
        return args.func(args)
    except UsageError as exc:
        print(f"swarm-gs {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:  # a disk, socket or permission failure after the checks: one line, no traceback
        print(f"swarm-gs {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # a second Ctrl-C in fly (emergency stop) or one outside a flight
        print(f"swarm-gs {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
