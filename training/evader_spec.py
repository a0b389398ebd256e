"""What ``--evader`` names: the evaders a pursuer team is evaluated against.

=====================  ======================================================================================
``learned``            the co-trained evader actors of the run or models folder (needs ``--run``/``--models``)
``scripted``           ``training.baselines.FleeingEvaders`` (flee the team, avoid walls and obstacles)
``both``               ``learned`` and ``scripted``
``all``                ``learned``, ``scripted`` and every kind of the suite (the headline table)
``A+B``                the kinds of A, then those of B (e.g. ``scripted+suite:hider``)
``suite``              every kind of the held-out suite (``training.evader_suite.SUITE``), each reported
                       alone, and the suite's mean
``suite:KIND[,KIND]``  those kinds of the suite
``module:Class``       a user's evader policy: ``Class`` from an importable module, built with ``Class(seed=S)``
``path/file.py:Class``  if it takes ``seed``, else ``Class()``; it has ``act(obs, env) -> [B, N, 2]`` (the
                       baselines' protocol; only the evader columns are used)
=====================  ======================================================================================
"""
from __future__ import annotations

import importlib
import importlib.util
import inspect
import sys
from pathlib import Path
from typing import Any

import numpy as np

from training.baselines import FleeingEvaders, Policy
from training.evader_suite import SUITE, make_suite_evader, parse_suite

BUILTIN = ("learned", "scripted", "both", "all", "suite")
SUITE_MEAN = "suite_mean"
"""The key (and column) of the suite's mean over its kinds."""


class EvaderSpecError(ValueError):
    """``--evader`` names nothing that can be evaluated against; the message says what to give instead."""


def _fix() -> str:
    return (f"give one of {list(BUILTIN)}, 'suite:KIND' (KIND in {list(SUITE)}), 'module:Class' or "
            f"'path/to/file.py:Class'")


def is_custom(spec: str) -> bool:
    return ":" in spec and not spec.startswith("suite")


def expand(spec: str) -> list[str]:
    """The evader kinds one ``--evader`` value stands for, each evaluated on its own."""
    if "+" in spec:
        kinds: list[str] = []
        for part in spec.split("+"):
            try:
                kinds += [k for k in expand(part.strip()) if k not in kinds]
            except EvaderSpecError as exc:
                raise EvaderSpecError(f"--evader {spec!r}: in it, {str(exc).removeprefix('--evader ')}") from None
        return kinds
    if spec == "all":
        return ["learned", "scripted", *(f"suite:{k}" for k in SUITE)]
    if spec == "both":
        return ["learned", "scripted"]
    if spec in ("learned", "scripted"):
        return [spec]
    if spec == "suite" or spec.startswith("suite:"):
        try:
            return [f"suite:{k}" for k in parse_suite(spec)]
        except ValueError as exc:
            raise EvaderSpecError(f"--evader {spec!r}: {exc}") from None
    if is_custom(spec):
        return [spec]
    raise EvaderSpecError(f"--evader {spec!r} is not an evader: {_fix()}")


def label(kind: str) -> str:
    """The short name of a kind in tables and JSON keys: ``suite:wanderer`` -> ``wanderer``."""
    return kind[len("suite:"):] if kind.startswith("suite:") else kind


def make_evaders(kind: str, seed: int, learned: Policy | None = None) -> Policy:
    """A fresh evader policy of one expanded kind; the same ``(kind, seed)`` gives the same evaders."""
    if kind == "learned":
        if learned is None:
            raise EvaderSpecError("--evader 'learned' needs the co-trained evaders of --run RUN or --models DIR: "
                                  "give one, or use --evader scripted / suite")
        return learned
    if kind == "scripted":
        return FleeingEvaders()
    if kind.startswith("suite:"):
        return make_suite_evader(label(kind), seed)
    return CheckedEvaders(kind, load_custom(kind, seed))


def load_custom(spec: str, seed: int) -> Any:
    """``module:Class`` or ``path/file.py:Class``, instantiated; errors name ``--evader``, the value and the fix."""
    target, _, name = spec.rpartition(":")
    if not target or not name.isidentifier():
        raise EvaderSpecError(f"--evader {spec!r}: expected module:Class or path/to/file.py:Class")
    if target.endswith(".py") or "/" in target or "\\" in target:
        path = Path(target)
        if not path.is_file():
            raise EvaderSpecError(f"--evader {spec!r}: no file {target!r}: give path/to/file.py:Class "
                                  f"(relative to the current directory) or module:Class")
        mod_name = f"_swarm_user_evader_{abs(hash(str(path.resolve())))}"
        try:
            mspec = importlib.util.spec_from_file_location(mod_name, path)
            module = importlib.util.module_from_spec(mspec)
            sys.modules[mod_name] = module
            mspec.loader.exec_module(module)
        except Exception as exc:  # the user's file may raise anything while it runs
            raise EvaderSpecError(f"--evader {spec!r}: importing {target} failed with {type(exc).__name__}: "
                                  f"{exc}: fix the file") from None
    else:
        try:
            module = importlib.import_module(target)
        except ImportError as exc:
            raise EvaderSpecError(f"--evader {spec!r}: cannot import {target!r} ({exc}): put the module on "
                                  f"PYTHONPATH or give path/to/file.py:Class") from None
        except Exception as exc:  # the user's module may raise anything while it runs
            raise EvaderSpecError(f"--evader {spec!r}: importing {target} failed with {type(exc).__name__}: "
                                  f"{exc}: fix the module") from None
    cls = getattr(module, name, None)
    if cls is None:
        raise EvaderSpecError(f"--evader {spec!r}: {target} has no {name!r}: give the name of a class defined "
                              f"there")
    try:
        takes_seed = "seed" in inspect.signature(cls).parameters
    except (TypeError, ValueError):
        takes_seed = False
    try:
        obj = cls(seed=seed) if takes_seed else cls()
    except Exception as exc:  # the user's constructor may raise anything
        raise EvaderSpecError(f"--evader {spec!r}: {name}({'seed=' + str(seed) if takes_seed else ''}) raised "
                              f"{type(exc).__name__}: {exc}: it must build with no arguments or seed=") from None
    if not callable(getattr(obj, "act", None)):
        raise EvaderSpecError(f"--evader {spec!r}: {name} has no act(obs, env) method: give a class with "
                              f"act(obs, env) -> [B, N, 2] (see training.baselines.Policy)")
    return obj


class CheckedEvaders:
    """A user's evaders with their output checked: ``[B, N, 2]`` finite numbers (the world clips to [-1, 1])."""

    def __init__(self, spec: str, inner: Any) -> None:
        self.spec = spec
        self.inner = inner

    def act(self, obs: np.ndarray, env) -> np.ndarray:
        try:
            a = np.asarray(self.inner.act(obs, env), dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise EvaderSpecError(f"--evader {self.spec!r}: act(obs, env) failed with {type(exc).__name__}: "
                                  f"{exc}: it must return [B, N, 2] numbers") from None
        want = (obs.shape[0], env.n_agents, 2)
        if a.shape != want:
            raise EvaderSpecError(f"--evader {self.spec!r}: act returned shape {a.shape}, expected {want} "
                                  f"([B, N, 2]: every agent's row; only the evader rows are used)")
        return a
