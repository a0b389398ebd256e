"""``swarm-gs fly / land / status``: the commands over a fleet file (real drones)."""
from __future__ import annotations

import argparse
import signal
import sys
import threading

from groundstation.cli_common import (UsageError, add_no_separation, add_view, check_actor_files, check_fence_arena,
                                      opt_str, read_input)
from runtime.cliutil import out_file, positive_float
from runtime.spec import SpecError


def _add_fleet_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--fleet", required=True, metavar="TOML",
                   help="fleet file: drones by URI and team, models, fence (see configs/fleet_example.toml)")


def _load_fleet(path: str, flying: bool = False):
    """The fleet file's fleet and flight tables, checked before any radio opens; with ``flying`` also the
    separation table and every file it names (models, spec, fence, anchors), which ``fly`` reads again.
    A wrong one is a ``UsageError`` naming ``--fleet`` and the key."""
    from groundstation.fleet import FleetConfig, load_separation, obstacles_from_fence
    from groundstation.positioning import AnchorLayout
    from groundstation.safety import FenceConfig
    from runtime.policy import PolicyError, read_manifest
    from runtime.spec import SwarmSpec
    fleet, flight = read_input("--fleet", path, FleetConfig.from_toml)
    _check_schemes(path, fleet)
    if not flying:
        return fleet, flight, None
    separation = read_input("--fleet", path, load_separation)
    where = f"--fleet {path}: fleet"
    try:
        manifest = read_manifest(fleet.models)
    except PolicyError as exc:
        raise UsageError(f"{where}.models: {exc}") from None
    check_actor_files(f"{where}.models", manifest)
    spec = read_input(f"{where}.spec", fleet.spec, SwarmSpec.from_toml, ("spec",)) if fleet.spec else SwarmSpec()
    if spec.hash != manifest.spec.hash:  # preflight refuses it too, once every radio link is up
        raise UsageError(f"{where}.spec: spec {spec.hash} ({fleet.spec or 'the default spec'}), but the models in "
                         f"{fleet.models} were exported for spec {manifest.spec.hash}: set fleet.spec to the spec "
                         f"they were trained on")
    fence = read_input(f"{where}.fence", fleet.fence, lambda p: FenceConfig.from_toml(p, spec=manifest.spec),
                       ("fence",))
    check_fence_arena(fence, manifest.spec, f"{where}.fence {fleet.fence}", f"the models in {fleet.models}")
    if fleet.anchors:
        read_input(f"{where}.anchors", fleet.anchors, lambda p: AnchorLayout.from_toml(p, fence=fence), ("lps",))
    try:
        obstacles_from_fence(fence, spec)
    except SpecError as exc:
        raise UsageError(f"{where}.fence {fleet.fence}: {exc}") from None
    return fleet, flight, separation


def _check_schemes(path: str, fleet) -> None:
    """Every drone's URI names a link the ground station has (open_link would say so only once per drone, after
    the others' radios were opened)."""
    from groundstation.link import scheme_of, schemes
    for k, drone in enumerate(fleet.drones):
        if scheme_of(drone.uri) not in schemes():
            raise UsageError(f"--fleet {path}: fleet.drones[{k}].uri: {drone.uri!r} has no known link scheme; write "
                             f"it as one of {', '.join(s + ':' for s in schemes())}, e.g. radio://0/80/2M/E7E7E7E701, "
                             f"udp://127.0.0.1:19850 or mavlink:udpin:127.0.0.1:14550")


def _add_fly(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("fly", help="fly real drones (radio:// URIs from a fleet file)",
                              description="Preflight, role assignment, staggered takeoff, the mission with the "
                                          "exported actors, landing. Ctrl-C lands everyone; a second Ctrl-C cuts "
                                          "every motor (emergency stop).")
    _add_fleet_arg(p)
    p.add_argument("--duration", type=positive_float, default=60.0, help="mission time [s] (default 60)")
    p.add_argument("--log", type=out_file, default=None, metavar="PATH",
                   help="write the flight log here: MCAP for Foxglove when PATH ends in .mcap, else JSON lines "
                        "(.jsonl)")
    add_view(p)
    add_no_separation(p)
    p.set_defaults(func=_run_fly)


def _fleet_errors():
    from groundstation.flight import PreflightError
    from groundstation.link import LinkError
    from runtime.policy import PolicyError
    from groundstation.liveview.server import ViewError
    from runtime.spec import SpecError
    return (PreflightError, LinkError, PolicyError, SpecError, ViewError)


def _run_fly(args: argparse.Namespace) -> int:
    import dataclasses

    from groundstation.fleet import fly
    fleet, flight, separation = _load_fleet(args.fleet, flying=True)
    if args.no_separation:
        separation = dataclasses.replace(separation, enabled=False)
    stop = threading.Event()
    presses = []

    def on_sigint(signum, frame):
        presses.append(signum)
        if len(presses) == 1:
            print("landing everyone (Ctrl-C again: emergency stop)", file=sys.stderr, flush=True)
            stop.set()
        else:
            signal.signal(signal.SIGINT, signal.default_int_handler)
            raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGINT, on_sigint)
        try:
            res = fly(fleet, flight, args.duration, opt_str(args.log), stop, separation=separation, echo=print,
                      view_port=args.view)
        finally:
            signal.signal(signal.SIGINT, previous)
    except _fleet_errors() as exc:
        print(f"swarm-gs fly: error: {exc}", file=sys.stderr)
        return 2
    for t, drone, kind, detail in res["events"]:
        print(f"  t={t:8.2f} s {drone or '':>6} {kind}: {detail}")
    sep = res["separation"]
    sep_line = (f"separation: {sep['solves']} solves, {sep['braked_setpoints']} braked setpoints" if sep["enabled"]
                else "separation OFF (--no-separation)")
    print(f"final: {res['final_status']}; geofence violations {res['geofence_violations']}; {sep_line}")
    return 0


def _add_land(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("land", help="land every drone of a fleet that is still flying")
    _add_fleet_arg(p)
    p.set_defaults(func=_run_land)


def _over_fleet(args: argparse.Namespace, what):
    """``what(fleet)`` over the fleet file's drones; None after printing a fleet error (exit status 2)."""
    fleet, _, _ = _load_fleet(args.fleet)
    try:
        return what(fleet)
    except _fleet_errors() as exc:
        print(f"swarm-gs {args.command}: error: {exc}", file=sys.stderr)
        return None


def _run_land(args: argparse.Namespace) -> int:
    from groundstation.fleet import land_fleet
    out = _over_fleet(args, land_fleet)
    if out is None:
        return 2
    for d, s in out.items():
        print(f"{d}: {s}")
    return 0


def _add_status(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("status", help="connect to every drone of a fleet and print its state")
    _add_fleet_arg(p)
    p.set_defaults(func=_run_status)


def _run_status(args: argparse.Namespace) -> int:
    from groundstation.fleet import fleet_status
    rows = _over_fleet(args, fleet_status)
    if rows is None:
        return 2
    for r in rows:
        pos = "-" if r["position"] is None else "(" + ", ".join(f"{c:+.2f}" for c in r["position"]) + ")"
        print(f"{r['drone']:>6} {r['uri']:<32} {r['team']:<8} {r['state']:<9} {r['battery_v'] or '-':>5} V  "
              f"{pos}  var {r['position_variance'] if r['position_variance'] is not None else '-'}  "
              f"fence {r['fence']}  link {r['link_quality']}  {r['telemetry_per_s']}/s")
    return 0
