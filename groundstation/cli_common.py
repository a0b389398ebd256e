"""What every ``swarm-gs`` subcommand shares: the usage error, reading and checking input files before any
drone flies, and the options several subcommands take."""
from __future__ import annotations

import argparse

from runtime.cliutil import check_in_file, port
from runtime.spec import SpecError


class UsageError(Exception):
    """A bad argument or input file found before any drone flies; the message names the option and the fix."""


def check_port_range(option: str, base: int, n: int, count_option: str = "--drones") -> None:
    """Drone i listens on ``base + i``: the last one must still be a port."""
    if n > 65535:
        raise UsageError(f"{count_option} {n}: more drones than UDP ports (one each from {option} {base}); give at "
                         f"most {65536 - base}")
    if n and base + n - 1 > 65535:
        raise UsageError(f"{option}: {base} + {n} drones passes port 65535; use a base port <= {65536 - n}")


def add_view(p: argparse.ArgumentParser) -> None:
    from groundstation.liveview.server import DEFAULT_PORT
    p.add_argument("--view", nargs="?", type=port, const=DEFAULT_PORT, default=None, metavar="PORT",
                   help=f"serve the live view on http://127.0.0.1:PORT/ during the flight (default port "
                        f"{DEFAULT_PORT}): the arena, every drone, events, metrics; land all, land one, emergency "
                        f"stop")


def add_no_separation(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-separation", action="store_true",
                   help="fly without the separation filter, for comparison only: drones may touch and crash")


def read_input(option: str, path, load, tables: tuple[str, ...] = ()):
    """``load(path)``, with a missing or unreadable file, one without any of ``tables`` (the loaders would take
    their defaults: a wrong file passes silently) or a wrong value in it as a ``UsageError`` naming ``option``
    (the loaders' messages name the file and the key)."""
    from runtime.policy import PolicyError
    from runtime.spec import load_toml
    try:
        check_in_file(path)
    except argparse.ArgumentTypeError as exc:
        raise UsageError(f"{option}: {exc}") from None
    try:
        if tables and not set(tables) & set(load_toml(path)):
            raise UsageError(f"{option}: {str(path)!r} has no " + " or ".join(f"[{t}]" for t in tables)
                             + " table: is it the right file?")
        return load(path)
    except (SpecError, PolicyError) as exc:
        raise UsageError(f"{option}: {exc}") from None


def check_actor_files(option: str, manifest) -> None:
    """Every actor file of ``manifest`` is there and is the one exported (sha256): ``load_models`` checks it too,
    but only after the links are up and preflight passed."""
    import hashlib
    for entry in manifest.agents:
        if not entry.file.is_file():
            raise UsageError(f"{option}: no ONNX model at {str(entry.file)!r} (agent {entry.id}): re-export with "
                             f"`swarm-export onnx --run runs/NAME --out {manifest.folder}`")
        if hashlib.sha256(entry.file.read_bytes()).hexdigest() != entry.sha256:
            raise UsageError(f"{option}: {str(entry.file)!r} is not the file the manifest lists (sha256 differs): "
                             f"it was damaged or replaced; re-export with `swarm-export onnx --run runs/NAME --out "
                             f"{manifest.folder}`")


def opt_str(path) -> str | None:
    return None if path is None else str(path)


def check_fence_arena(fence, spec, fence_name: str, models_name: str) -> None:
    """``fence.check_arena`` as a ``UsageError``: a fence that cuts the models' arena by more than its margin."""
    from groundstation.fence import check_arena
    try:
        check_arena(fence, spec, fence_name, models_name)
    except SpecError as exc:
        raise UsageError(str(exc)) from None
