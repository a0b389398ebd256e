"""``swarm-gs``: the ground station's command line.

Each subcommand registers itself in one function ``_add_<name>(subparsers)`` that sets ``func``; add a
subcommand by writing one such function and listing it in ``SUBCOMMANDS``.
"""
from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time

from groundstation.sim.swarm import DEFAULT_BASE_PORT, SimError, SimSwarm


def _add_sim(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "sim", help="run simulated Crazyflies (CRTP over UDP) for any cflib client",
        description="Start N simulated Crazyflies on UDP ports base-port+i. Connect with cflib as "
                    "udp://HOST:PORT, e.g. SyncCrazyflie('udp://127.0.0.1:19850'). Ctrl-C stops them.")
    p.add_argument("--drones", type=int, default=1, help="number of drones (default 1)")
    p.add_argument("--base-port", type=int, default=DEFAULT_BASE_PORT,
                   help=f"UDP port of drone 0 (default {DEFAULT_BASE_PORT}, where cflib scans)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the positioning noise (default 0)")
    p.add_argument("--spacing", type=float, default=0.5, help="distance between start positions [m]")
    p.add_argument("--duration", type=float, default=None,
                   help="stop after this many seconds (default: run until Ctrl-C)")
    p.set_defaults(func=_run_sim)


def _run_sim(args: argparse.Namespace) -> int:
    sims = SimSwarm(args.drones, base_port=args.base_port, host=args.host, seed=args.seed, spacing=args.spacing)
    try:
        sims.start()
    except SimError as exc:
        print(f"swarm-gs sim: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print(f"{args.drones} simulated Crazyflies:", flush=True)
    for uri in sims.uris:
        print(f"  {uri}", flush=True)
    try:
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            stop.wait(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        sims.stop()
    print("simulators stopped", flush=True)
    return 0


SUBCOMMANDS = (_add_sim,)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="swarm-gs", description="swarmpursuit ground station")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    subparsers = parser.add_subparsers(dest="command", required=True)
    for add in SUBCOMMANDS:
        add(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
