"""The actor checkpoint: what training hands to export, evaluation and the demo.

``actors.pt`` (a ``torch.save`` dict) holds:

- ``format``: 1
- ``spec``: ``SwarmSpec.to_dict()``; ``spec_hash``: ``SwarmSpec.hash``
- ``agents``: a list of ``{"id", "role", "obs_dim", "hidden", "state_dict"}``, one per agent in spec order;
  ``state_dict`` is that of ``training.networks.Actor(obs_dim, 2, hidden)`` whose first layer takes exactly
  ``spec.obs_dim(role)`` inputs (no padding)
- ``config``: the training config as a plain dict; ``meta``: free-form (git revision, steps, evaluation)
"""
from __future__ import annotations

import errno
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from runtime.spec import Role, SpecError, SwarmSpec
from training.networks import Actor

FORMAT = 1


class CheckpointError(ValueError):
    """An actor checkpoint is missing, unreadable or does not match its spec."""


class CheckpointWriteError(OSError):
    """A checkpoint could not be written (a full disk, most often); what was on disk before is kept whole."""


def save_torch_files(items: Sequence[tuple[Any, str | Path]], fix: str = "free some space and run again") -> None:
    """``torch.save`` each ``(object, path)`` all or nothing: every file is first written beside its place as
    ``PATH.tmp``, and only once all are written are they renamed over the old ones, so that a failure (a full
    disk: torch reports it as a RuntimeError from its zip writer) leaves the previous files whole, matching each
    other, and no partial file behind. Raises ``CheckpointWriteError`` naming the file, the free space and
    ``fix``."""
    done: list[tuple[Path, Path]] = []
    for obj, path in items:
        p = Path(path)
        tmp = p.with_suffix(p.suffix + ".tmp")
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            done.append((tmp, p))
            torch.save(obj, tmp)
        except (OSError, RuntimeError) as exc:
            for t, _ in done:
                t.unlink(missing_ok=True)
            try:
                free = f"{shutil.disk_usage(p.parent).free / 1e6:.0f} MB free there"
            except OSError:
                free = "its disk unreadable"
            raise CheckpointWriteError(
                getattr(exc, "errno", None) or errno.EIO,
                f"could not write {str(p)!r} ({' '.join(str(exc).split())[:160]}; {free}); what was there before is "
                f"kept as it was: {fix}") from exc
    for tmp, p in done:
        tmp.replace(p)


def save_actors(path: str | Path, spec: SwarmSpec, actors: list[Actor], config: dict[str, Any] | None = None,
                meta: dict[str, Any] | None = None) -> Path:
    ids = spec.team.agent_ids()
    if len(actors) != len(ids):
        raise CheckpointError(f"expected {len(ids)} actors (one per agent), got {len(actors)}")
    agents = []
    for aid, role, actor in zip(ids, spec.roles, actors):
        if actor.obs_dim != spec.obs_dim(role):
            raise CheckpointError(f"actor {aid} takes {actor.obs_dim} inputs, the spec's {role.label} layout has "
                                  f"{spec.obs_dim(role)}")
        agents.append({"id": aid, "role": role.label, "obs_dim": actor.obs_dim, "hidden": list(actor.hidden),
                       "state_dict": {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}})
    doc = {"format": FORMAT, "spec": spec.to_dict(), "spec_hash": spec.hash, "agents": agents,
           "config": config or {}, "meta": meta or {}}
    p = Path(path)
    save_torch_files([(doc, p)])
    return p


def load_actors(path: str | Path) -> tuple[SwarmSpec, list[tuple[str, Role, Actor]], dict[str, Any]]:
    """(spec, [(agent_id, role, actor)], the whole document without state dicts)."""
    p = Path(path)
    if p.is_dir():
        p = p / "actors.pt"
    if not p.is_file():
        raise CheckpointError(f"no actor checkpoint at {str(p)!r}: train with `swarm-train train --out RUN` first")
    try:
        doc = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds for a corrupted file
        raise CheckpointError(f"cannot read actor checkpoint {str(p)!r}: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise CheckpointError(f"{str(p)!r} is not an actor checkpoint of format {FORMAT}")
    try:
        spec = SwarmSpec.from_dict(doc["spec"])
    except SpecError as exc:
        raise CheckpointError(f"{str(p)!r}: its spec is invalid: {exc}") from None
    if spec.hash != doc.get("spec_hash"):
        raise CheckpointError(f"{str(p)!r}: stored spec hash {doc.get('spec_hash')} does not match its spec "
                              f"({spec.hash}); the file was edited or written by another version")
    out = []
    for a in doc["agents"]:
        role = Role.parse(a["role"])
        actor = Actor(int(a["obs_dim"]), 2, tuple(a["hidden"]))
        actor.load_state_dict(a["state_dict"])
        actor.eval()
        out.append((a["id"], role, actor))
    meta = {k: v for k, v in doc.items() if k != "agents"}
    return spec, out, meta
