"""ONNX export of trained actors: one file per agent, weights inside, spec metadata, parity-checked.

``export_run(run_dir, out_dir)`` reads ``run_dir/actors.pt`` (``training.checkpoint``) and writes

- ``out_dir/<agent_id>.onnx``: input ``obs`` ``[batch, obs_dim]`` float32 (dynamic batch), output ``action``
  ``[batch, 2]``; metadata_props ``spec_hash``, ``role``, ``agent_id``, ``spec_json``, ``obs_dim``, ``act_dim``
  (the runtime and the C generator rely on exactly these);
- ``out_dir/manifest.json``: ``{"format": 1, "spec_hash", "spec", "agents": [{"id", "role", "file", "sha256",
  "obs_dim"}], "config", "evaluation", "parity"}``.

Every file passes ``onnx.checker`` and matches torch within ``PARITY_TOL`` (max absolute difference) on
``n_random`` observations drawn uniformly within the layout's bounds and ``n_recorded`` observations recorded
from a rollout of the actors themselves in ``runtime.world`` (through the one encoder). A mismatch is an
``ExportError``; nothing is written in that case.

Agents that share an architecture share one traced graph: the dynamo exporter runs once per
``(obs_dim, hidden)`` and each agent's weights are written into a copy of that graph's initializers, which
the parity check then verifies against the agent's own torch module.
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import hashlib
import io
import json
import logging
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import numpy_helper

from firmware_export.observations import random_observations, simulate
from runtime.spec import Role, SwarmSpec
from training.checkpoint import CheckpointError, load_actors
from training.networks import Actor

log = logging.getLogger(__name__)

MANIFEST_FORMAT = 1
OPSET = 18
PARITY_TOL = 5e-5
"""Largest |onnxruntime - torch| accepted on an action in [-1, 1]. Both compute in float32 with their own
summation order: over two 64-wide layers fed observations of up to a few metres that differs by up to ~2e-5
(measured 1.3e-5 and 1.7e-5 on models/paper_flight's pursuer_1 with random observations of seeds 0 and 1),
while a graph that computes anything else differs by 1e-2 or more."""
INPUT_NAME = "obs"
OUTPUT_NAME = "action"
EVALUATION_FILES = ("evaluation.json", "eval.json", "results.json")
"""Files in a run folder, in order of preference, whose JSON becomes the manifest's ``evaluation``."""


class ExportError(RuntimeError):
    """Export failed: the checkpoint is unusable, the graph is invalid or does not match torch."""


# --------------------------------------------------------------------------------------------------
# tracing


def _trace(actor: Actor) -> onnx.ModelProto:
    """The dynamo exporter's graph of ``actor`` with a dynamic batch axis."""
    dummy = torch.zeros(1, actor.obs_dim)
    batch = torch.export.Dim("batch")
    # the exporter chats on stdout/stderr and warns about optional packages; keep the CLI quiet
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        prog = torch.onnx.export(actor.eval(), (dummy,), dynamo=True, external_data=False,
                                 input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
                                 dynamic_shapes=({0: batch},), opset_version=OPSET, verbose=False)
    model = prog.model_proto
    del model.metadata_props[:]  # drop the exporter's internal metadata; ours is the contract
    for vi in list(model.graph.input) + list(model.graph.output):
        del vi.metadata_props[:]
    return model


def _with_weights(template: onnx.ModelProto, actor: Actor) -> onnx.ModelProto:
    """A copy of ``template`` whose initializers hold ``actor``'s parameters (matched by name)."""
    model = copy.deepcopy(template)
    params = {k: v.detach().cpu().numpy() for k, v in actor.state_dict().items()}
    names = {init.name for init in model.graph.initializer}
    if names != set(params):
        raise ExportError(f"traced graph initializers {sorted(names)} do not match the actor's parameters "
                          f"{sorted(params)}: the Actor architecture changed; update the exporter")
    for init in model.graph.initializer:
        arr = params[init.name].astype(np.float32)
        init.CopyFrom(numpy_helper.from_array(arr, init.name))
    return model


def _annotate(model: onnx.ModelProto, spec: SwarmSpec, agent_id: str, role: Role, obs_dim: int) -> None:
    meta = {"spec_hash": spec.hash, "role": role.label, "agent_id": agent_id,
            "spec_json": json.dumps(spec.to_dict(), sort_keys=True), "obs_dim": str(obs_dim),
            "act_dim": str(spec.act_dim)}
    for k, v in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    model.producer_name = "swarmpursuit.firmware_export"
    model.doc_string = f"swarmpursuit actor {agent_id} ({role.label}), spec {spec.hash}"


# --------------------------------------------------------------------------------------------------
# parity


def flown_observations(spec: SwarmSpec, actors: list[Actor], n: int, seed: int = 0) -> list[np.ndarray]:
    """Per agent, ``n`` float32 observations ``[n, obs_dim]`` recorded while the trained actors fly in the world
    (``observations.simulate``): ``ceil(n / 100)`` envs run for 100 steps (episodes reset every
    ``spec.timing.episode_steps``)."""
    steps = 100
    n_envs = max(1, -(-n // steps))
    dims = [spec.obs_dim(r) for r in spec.roles]
    rec = [np.empty((n_envs * steps, d), dtype=np.float32) for d in dims]
    actions = np.zeros((n_envs, spec.n_agents, 2))

    def fly(obs: np.ndarray) -> np.ndarray:
        for i, actor in enumerate(actors):
            actions[:, i] = actor(torch.from_numpy(obs[:, i, :dims[i]].astype(np.float32))).numpy()
        return actions

    with torch.no_grad():
        for k, obs in zip(range(steps), simulate(spec, n_envs, seed, fly)):
            for i in range(len(actors)):
                rec[i][k * n_envs:(k + 1) * n_envs] = obs[:, i, :dims[i]]
    return [r[:n] for r in rec]


def parity(model: onnx.ModelProto, actor: Actor, obs: np.ndarray) -> float:
    """Max absolute difference between onnxruntime and torch on ``obs`` ``[n, obs_dim]`` float32."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    sess = ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    got = sess.run([OUTPUT_NAME], {INPUT_NAME: obs})[0]
    with torch.no_grad():
        want = actor(torch.from_numpy(obs)).numpy()
    if got.shape != want.shape:
        raise ExportError(f"onnxruntime returned shape {got.shape}, torch {want.shape}")
    return float(np.max(np.abs(got.astype(np.float64) - want.astype(np.float64))))


# --------------------------------------------------------------------------------------------------
# the run folder -> models folder


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _evaluation(run: Path, meta: dict[str, Any]) -> Any:
    inner = meta.get("meta") or {}
    if isinstance(inner, dict) and inner.get("evaluation") is not None:
        return inner["evaluation"]
    for name in EVALUATION_FILES:
        p = run / name
        if p.is_file():
            try:
                return json.loads(p.read_text())
            except (OSError, json.JSONDecodeError) as exc:
                log.warning("ignoring unreadable evaluation file %s: %s", p, exc)
    return None


def export_run(run_dir: str | Path, out_dir: str | Path, n_random: int = 10_000, n_recorded: int = 10_000,
               seed: int = 0, tol: float = PARITY_TOL) -> dict[str, Any]:
    """Export every actor of ``run_dir/actors.pt`` into ``out_dir``; returns the manifest written."""
    run = Path(run_dir)
    try:
        spec, agents, meta = load_actors(run)
    except CheckpointError as exc:
        raise ExportError(str(exc)) from None
    out = Path(out_dir)
    rng = np.random.default_rng(seed)
    actors = [a for _, _, a in agents]
    recorded = flown_observations(spec, actors, n_recorded, seed) if n_recorded else [None] * len(actors)
    templates: dict[tuple[int, tuple[int, ...]], onnx.ModelProto] = {}
    models: list[tuple[str, Role, int, onnx.ModelProto]] = []
    report: dict[str, dict[str, float]] = {}
    for (aid, role, actor), rec in zip(agents, recorded):
        key = (actor.obs_dim, actor.hidden)
        if key not in templates:
            log.info("tracing an actor with %d inputs and hidden %s", *key)
            templates[key] = _trace(actor)
        model = _with_weights(templates[key], actor)
        _annotate(model, spec, aid, role, actor.obs_dim)
        try:
            onnx.checker.check_model(model, full_check=True)
        except onnx.checker.ValidationError as exc:
            raise ExportError(f"{aid}: the exported graph fails onnx.checker: {exc}") from None
        figures = {"random_max_abs_diff": parity(model, actor, random_observations(spec, role, n_random, rng))}
        if rec is not None:
            figures["recorded_max_abs_diff"] = parity(model, actor, rec)
        worst = max(figures.values())
        if not worst <= tol:
            raise ExportError(f"{aid}: onnxruntime and torch differ by {worst:.3g} (> {tol:g}) on "
                              f"{'random' if figures['random_max_abs_diff'] == worst else 'recorded'} "
                              f"observations: the graph does not compute the actor; nothing was written")
        report[aid] = figures
        models.append((aid, role, actor.obs_dim, model))
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for aid, role, dim, model in models:
        path = out / f"{aid}.onnx"
        tmp = path.with_suffix(".onnx.tmp")
        tmp.write_bytes(model.SerializeToString())
        os.replace(tmp, path)
        entries.append({"id": aid, "role": role.label, "file": path.name, "sha256": sha256_file(path),
                        "obs_dim": dim})
    manifest = {"format": MANIFEST_FORMAT, "spec_hash": spec.hash, "spec": spec.to_dict(), "agents": entries,
                "config": meta.get("config") or {}, "evaluation": _evaluation(run, meta),
                "parity": {"tolerance": tol, "n_random": n_random, "n_recorded": n_recorded, "agents": report}}
    tmp = out / "manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=False))
    os.replace(tmp, out / "manifest.json")
    log.info("wrote %d ONNX actors and manifest.json to %s (spec %s)", len(entries), out, spec.hash)
    return manifest


# --------------------------------------------------------------------------------------------------
# `swarm-export onnx` (firmware_export.cli.add_onnx declares its arguments without importing torch)


def run_onnx_command(args: argparse.Namespace) -> int:
    """``swarm-export onnx``: prints a summary; a bad run folder is one line on stderr and exit code 2."""
    import sys
    try:
        m = export_run(args.run, args.out, args.random, args.recorded, args.seed)
    except ExportError as exc:
        print(f"swarm-export onnx: {exc}", file=sys.stderr)
        return 2
    worst = max(max(v.values()) for v in m["parity"]["agents"].values())
    print(f"wrote {len(m['agents'])} actors + manifest.json to {args.out} (spec {m['spec_hash']}); parity "
          f"max |onnx - torch| = {worst:.2e} on {args.random} random + {args.recorded} recorded observations")
    return 0
