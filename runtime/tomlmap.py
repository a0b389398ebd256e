"""TOML tables onto frozen dataclasses, strictly: an unknown key, a wrong type or an impossible value is a
``SpecError`` that names the field (``where.key``) and says how to fix it. ``runtime.spec`` and every config
dataclass of the other packages (``FlightConfig``, ``FenceConfig``, ``TrainConfig``, ...) load through it."""
from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, Mapping


class SpecError(ValueError):
    """A spec or config value is wrong. The message names the field and says how to fix it."""


SECTION_NAMES: dict[str, str] = {}
"""Dataclass name -> the table name its own validation messages start with (``arena.half_width: ...``), so that
``from_mapping`` can put the full path in front (``spec.arena.half_width: ...``); ``runtime.spec`` fills it."""


def load_toml(path: str | Path) -> dict[str, Any]:
    p = Path(path)
    if p.is_dir():
        raise SpecError(f"config file {str(p)!r} is a folder: give the TOML file in it")
    if not p.is_file():
        raise SpecError(f"config file {str(p)!r} does not exist: check the path")
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SpecError(f"config file {str(p)!r} is not valid TOML: {exc}") from None
    except OSError as exc:
        raise SpecError(f"config file {str(p)!r} cannot be read ({exc.strerror or exc}): check its permissions") \
            from None


def from_mapping(cls: type, data: Mapping[str, Any], where: str, base: Any = None) -> Any:
    """Build frozen dataclass ``cls`` from ``data``; unknown keys, wrong types and impossible values raise
    ``SpecError`` naming ``where.key``. Keys missing from ``data`` come from ``base`` (or ``cls()``)."""
    if not isinstance(data, Mapping):
        raise SpecError(f"{where}: expected a table, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise SpecError(f"{where}.{unknown[0]}: unknown key; valid keys are {sorted(fields)}")
    if base is None:
        try:
            base = cls()
        except TypeError:
            base = None
    kwargs: dict[str, Any] = {n: getattr(base, n) for n in fields} if base is not None else {}
    for name, value in data.items():
        tp = hints[name]
        if dataclasses.is_dataclass(tp):
            kwargs[name] = from_mapping(tp, value, f"{where}.{name}", kwargs.get(name))
        else:
            kwargs[name] = _coerce(tp, value, f"{where}.{name}")
    missing = sorted(set(fields) - set(kwargs))
    if missing:
        raise SpecError(f"{where}.{missing[0]}: missing; set it in the [{where}] table")
    try:
        return cls(**kwargs)
    except SpecError as exc:
        msg = str(exc)
        sec = SECTION_NAMES.get(cls.__name__)
        if sec and msg.startswith(sec + "."):
            msg = where + msg[len(sec):]
        elif not msg.startswith(where):
            msg = f"{where}.{msg}"
        raise SpecError(msg) from None


def _coerce(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return from_mapping(tp, value, where)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(args[0], value, where)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise SpecError(f"{where}: expected a list, got {type(value).__name__} {value!r}")
        args = typing.get_args(tp)
        inner = args[0] if args else Any
        return tuple(_coerce(inner, v, f"{where}[{i}]") for i, v in enumerate(value))
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SpecError(f"{where}: expected a number, got {type(value).__name__} {value!r}")
        if not math.isfinite(value):
            raise SpecError(f"{where}: must be finite, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SpecError(f"{where}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise SpecError(f"{where}: expected true or false, got {type(value).__name__} {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise SpecError(f"{where}: expected a string, got {type(value).__name__} {value!r}")
        return value
    return value
