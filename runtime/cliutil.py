"""What every command line of the project shares: argument types that check values before any work starts,
a parser whose errors are one line, and atomic file writes.

A bad argument ends the command with exactly one line on stderr that names the argument, the value given and
what to give instead, and exit status 2 (``EXIT_USAGE``), e.g.::

    swarm-runtime bench: error: argument --idle: expected a finite number > 0 (seconds), got 'inf'

Output paths are checked at parse time (``out_file``, ``out_dir``): a path below an existing file, or a file
where a folder is needed, is a usage error before a minute of training or flying is spent. Files are written
with ``write_text_atomic``: a reader, an error or Ctrl-C sees the old file or the new one, never half of one.

Torch-free, like the rest of ``runtime``: every package's ``cli.py`` imports it.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator, NoReturn

EXIT_USAGE = 2
"""Exit status of a usage error (a bad argument, config value or input file), as argparse uses."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser with one-line errors: ``PROG: error: MESSAGE (see PROG --help)``, exit 2; argparse's
    own prints the usage block first, which buries the one line that says what is wrong."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {message} (see {self.prog} --help)\n")
        sys.exit(EXIT_USAGE)


# ------------------------------------------------------------------------------------------- numbers


def _number(text: str, kind: type, what: str) -> Any:
    try:
        v = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if isinstance(v, float) and not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return v


def int_at_least(low: int, unit: str = "") -> Callable[[str], int]:
    """An argparse type: a whole number >= ``low``."""
    what = f"a whole number >= {low}" + (f" ({unit})" if unit else "")

    def parse(text: str) -> int:
        v = _number(text, int, what)
        if v < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}" + (f" ({unit})" if unit else "") + f", got {text!r}")
        return v
    parse.__name__ = f"int >= {low}"
    return parse


def int_in(low: int, high: int, unit: str = "") -> Callable[[str], int]:
    """An argparse type: a whole number in ``low..high``."""
    what = f"a whole number in {low}..{high}" + (f" ({unit})" if unit else "")

    def parse(text: str) -> int:
        v = _number(text, int, what)
        if not low <= v <= high:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return v
    parse.__name__ = f"int in {low}..{high}"
    return parse


positive_int = int_at_least(1)
nonneg_int = int_at_least(0)

SEED_MAX = 2 ** 32 - 1
"""The largest seed a command takes: numpy takes any, but torch's generators overflow past 2**63 and legacy
seeding (``RandomState``) past 2**32 - 1; one bound for every ``--seed`` of the project."""


def seed(text: str) -> int:
    """An argparse type: a seed, a whole number in 0..``SEED_MAX``."""
    what = f"a seed, a whole number >= 0 and <= {SEED_MAX}"
    v = _number(text, int, what)
    if not 0 <= v <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return v


def recheck(args: argparse.Namespace, name: str, check: Callable[[str], Any]) -> None:
    """``check`` (an argparse type of this module) applied again to ``args.<name>`` when it is set: for an option
    registered elsewhere with a looser type. Raises ``argparse.ArgumentTypeError`` naming ``--<name>``."""
    value = getattr(args, name, None)
    if value is None or isinstance(value, bool):
        return
    try:
        check(str(value))
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"--{name.replace('_', '-')}: {exc}") from None


def float_in(low: float = -math.inf, high: float = math.inf, *, low_open: bool = False, high_open: bool = False,
             unit: str = "", allow_inf: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite float in [low, high] (``(low, high]`` with ``low_open``, ``[low, high)`` with
    ``high_open``); ``allow_inf`` also takes ``inf`` (e.g. an unlimited bandwidth)."""
    bounds = (f"> {low:g}" if low_open else f">= {low:g}") if high == math.inf else \
        f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    what = ("a number " if allow_inf else "a finite number ") + bounds + (f" ({unit})" if unit else "")

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        ok = (v > low if low_open else v >= low) and (v < high if high_open else v <= high) and not math.isnan(v)
        if not ok or (math.isinf(v) and not allow_inf):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return v
    parse.__name__ = what
    return parse


positive_float = float_in(0.0, low_open=True)
nonneg_float = float_in(0.0)
probability = float_in(0.0, 1.0)


def port(text: str) -> int:
    """An argparse type: a UDP/TCP port number, 1..65535."""
    v = _number(text, int, "a port number in 1..65535")
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port number in 1..65535, got {text!r}")
    return v


def float_list(item: Callable[[str], float], what: str, example: str) -> Callable[[str], list[float]]:
    """An argparse type: a non-empty comma-separated list, each item checked by ``item``."""
    def parse(text: str) -> list[float]:
        parts = [x.strip() for x in text.split(",")]
        if not text.strip() or any(not x for x in parts):
            raise argparse.ArgumentTypeError(f"expected a comma-separated list of {what} (e.g. {example}), "
                                             f"got {text!r}")
        try:
            return [item(x) for x in parts]
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentTypeError(f"expected a comma-separated list of {what} (e.g. {example}), got "
                                             f"{text!r}: {exc}") from None
    parse.__name__ = f"list of {what}"
    return parse


# --------------------------------------------------------------------------------------------- paths


def _blocking_file(path: Path) -> Path | None:
    """The first existing ancestor of ``path`` that is not a folder (nothing can be created below it)."""
    for parent in reversed(path.absolute().parents):
        if parent.exists() and not parent.is_dir():
            return parent
    return None


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists():
        p = p.parent
    return p


def _can_create_in(folder: Path) -> bool:
    """A file can be created in ``folder``: ``os.access`` first, then a real probe file (removed at once), since
    ``os.access`` says yes to root on a read-only mount or in ``/proc``, where the write would fail after the work."""
    if not os.access(folder, os.W_OK | os.X_OK):
        return False
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-check.", dir=folder)
    except OSError:
        return False
    os.close(fd)
    os.unlink(probe)
    return True


def check_out_file(path: str | Path) -> Path:
    """``path`` if a file can be written there: no ancestor is a file, it is not a folder, and the nearest
    existing folder is writable; otherwise ``argparse.ArgumentTypeError`` naming what is in the way."""
    p = Path(path)
    if not str(path).strip():
        raise argparse.ArgumentTypeError("expected a file path, got ''")
    block = _blocking_file(p)
    if block is not None:
        raise argparse.ArgumentTypeError(f"cannot write {str(path)!r}: {str(block)!r} is a file, not a folder; "
                                         f"give a path in a folder")
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"cannot write {str(path)!r}: it is a folder; give a file name in it")
    base = _nearest_existing(p.parent)
    if not _can_create_in(base):
        raise argparse.ArgumentTypeError(f"cannot write {str(path)!r}: folder {str(base)!r} is not writable; "
                                         f"give a path you can write")
    return p


def check_out_dir(path: str | Path) -> Path:
    """``path`` if it is or can become a writable folder (no file in the way); otherwise
    ``argparse.ArgumentTypeError``."""
    p = Path(path)
    if not str(path).strip():
        raise argparse.ArgumentTypeError("expected a folder path, got ''")
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"cannot write into {str(path)!r}: it is a file, not a folder; give a "
                                         f"folder path")
    block = _blocking_file(p)
    if block is not None:
        raise argparse.ArgumentTypeError(f"cannot create folder {str(path)!r}: {str(block)!r} is a file; give a "
                                         f"path in a folder")
    base = _nearest_existing(p)
    if not _can_create_in(base):
        raise argparse.ArgumentTypeError(f"cannot write into {str(path)!r}: {str(base)!r} is not writable; give a "
                                         f"folder you can write")
    return p


def check_in_file(path: str | Path) -> Path:
    """``path`` if it is an existing readable file; otherwise ``argparse.ArgumentTypeError``."""
    if not str(path).strip():  # Path("") is ".", which would read as "a folder"
        raise argparse.ArgumentTypeError("expected a file path, got ''")
    p = Path(path)
    if not p.exists():
        raise argparse.ArgumentTypeError(f"{str(path)!r} does not exist; check the path")
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{str(path)!r} is a folder, not a file; give the file in it")
    if not os.access(p, os.R_OK):
        raise argparse.ArgumentTypeError(f"{str(path)!r} is not readable; check its permissions")
    return p


def models_dir(text: str) -> Path:
    """An argparse type for a models folder of ``swarm-export onnx``: a file there is an error; a missing folder
    or one without a manifest is left to ``runtime.policy.read_manifest``, whose message says how to export."""
    if not text.strip():  # Path("") is the working directory
        raise argparse.ArgumentTypeError("expected a models folder path, got ''")
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a file, not a models folder; give the folder that "
                                         f"`swarm-export onnx --out DIR` wrote (manifest.json + one ONNX actor each)")
    return p


def out_file(text: str) -> Path:
    """An argparse type for an output file (``check_out_file``)."""
    return check_out_file(text)


PICTURE_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".eps", ".ps")
"""File types matplotlib's Agg backend writes (``savefig`` picks the format from the suffix)."""


def out_picture(text: str) -> Path:
    """An argparse type for a picture to draw (``check_out_file`` and a suffix in ``PICTURE_SUFFIXES``): a
    wrong suffix would fail in ``savefig`` only after the run it draws."""
    p = check_out_file(text)
    if p.suffix.lower() not in PICTURE_SUFFIXES:
        raise argparse.ArgumentTypeError(f"cannot draw {text!r}: unknown picture type {p.suffix or '(no suffix)'!r}; "
                                         f"end the name in one of {', '.join(PICTURE_SUFFIXES)}")
    return p


def out_dir(text: str) -> Path:
    """An argparse type for an output folder (``check_out_dir``)."""
    return check_out_dir(text)


def in_file(text: str) -> Path:
    """An argparse type for an input file (``check_in_file``)."""
    return check_in_file(text)


def out_prefix(*suffixes: str) -> Callable[[str], Path]:
    """An argparse type for an output path without suffix, written as PATH+suffix for each of ``suffixes``."""
    def parse(text: str) -> Path:
        if not text.strip():
            raise argparse.ArgumentTypeError("expected an output path without suffix, got ''")
        p = Path(text)
        for s in suffixes:
            check_out_file(p.with_suffix(s))
        return p
    parse.__name__ = "output path"
    return parse


# -------------------------------------------------------------------------------------------- writes


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Writes ``text`` to a temporary file beside ``path`` and renames it over ``path``: a reader (or a crash,
    an error or Ctrl-C half-way) sees the old file or the new one, never half of one. Creates the folder."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp's 0600 would make results unreadable to others
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` with the same suffix, for a writer that takes a file name (matplotlib's
    ``savefig``); renamed over ``path`` when the block ends, removed when it raises (or on Ctrl-C)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.stem}.", suffix=p.suffix, dir=p.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _read_umask()  # read once at import, before any thread: os.umask is process-wide


def json_safe(obj: Any) -> Any:
    """``obj`` with NaN -> None and +-inf -> "inf"/"-inf" (strict JSON has neither)."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None if math.isnan(obj) else ("inf" if obj > 0 else "-inf")
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def write_json_atomic(path: str | Path, obj: Any, sort_keys: bool = False) -> Path:
    """``obj`` as indented strict JSON at ``path``, atomically (``write_text_atomic``)."""
    return write_text_atomic(path, json.dumps(json_safe(obj), indent=2, sort_keys=sort_keys) + "\n")
