"""Read an exported actor (ONNX) into a plain list of dense layers, and its spec from the model's metadata.

The graph walk is ``runtime.mlp_graph`` (shared with the runtime's compiled engine): a chain of ``Gemm`` (or
``MatMul`` + ``Add``) with constant weights, each optionally followed by ``Relu`` or ``Tanh``. Anything else is
an ``UnsupportedGraph`` error naming the node.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from runtime import mlp_graph as graph
from runtime.mlp_graph import ACTIVATIONS, Dense  # noqa: F401 (re-exported: the C side's layer type)
from runtime.spec import Role, SpecError, SwarmSpec


class CExportError(ValueError):
    """Base of the C exporter's errors; the message says what is wrong and how to fix it."""


class ModelFileError(CExportError):
    """The model file is missing or is not an ONNX model."""


class UnsupportedGraph(CExportError):
    """The ONNX graph uses an operator or a structure the C generator does not translate."""


class ModelShapeError(CExportError):
    """Weights, input or output do not have the shapes the spec and the API require."""


class ModelMetadataError(CExportError):
    """The spec metadata (``spec_json``, ``spec_hash``, ``role``) is missing or inconsistent."""


@dataclass(frozen=True)
class ActorModel:
    layers: tuple[Dense, ...]
    spec: SwarmSpec
    role: Role
    agent_id: str
    source: str
    """Where the model came from (a path), for messages and generated comments."""

    @property
    def obs_dim(self) -> int:
        return self.layers[0].n_in

    @property
    def act_dim(self) -> int:
        return self.layers[-1].n_out


def load_onnx(path: str | Path):
    """The ``onnx.ModelProto`` at ``path``, or ``ModelFileError``."""
    import onnx  # export-only dependency

    p = Path(path)
    if not p.is_file():
        raise ModelFileError(f"model file {str(p)!r} does not exist: write it with `swarm-export onnx` or fix the path")
    try:
        model = onnx.load(str(p))
    except Exception as exc:  # onnx raises DecodeError, RuntimeError, ... depending on the damage
        raise ModelFileError(f"{str(p)!r} is not an ONNX model ({type(exc).__name__}: {exc}): pass the .onnx file "
                             f"written by `swarm-export onnx`") from None
    if not model.graph.node:
        raise ModelFileError(f"{str(p)!r} has an empty graph: pass the .onnx file written by `swarm-export onnx`")
    return model


def read_actor(path: str | Path, spec_toml: str | Path | None = None, role: str | None = None) -> ActorModel:
    """Layers, spec and role of the actor at ``path``, checked against each other."""
    model = load_onnx(path)
    layers = extract_layers(model, str(path))
    spec, role_v, agent_id = _read_metadata(model, str(path), spec_toml, role)
    want = spec.obs_dim(role_v)
    if layers[0].n_in != want:
        raise ModelShapeError(
            f"{path}: the first layer takes {layers[0].n_in} inputs, the spec's {role_v.label} layout has {want} "
            f"(spec {spec.hash}): export the actor trained with this spec, or pass the matching --spec-toml")
    if layers[-1].n_out != spec.act_dim:
        raise ModelShapeError(f"{path}: the model outputs {layers[-1].n_out} values, actions have {spec.act_dim}: "
                              f"export a training.networks.Actor with act_dim={spec.act_dim}")
    return ActorModel(tuple(layers), spec, role_v, agent_id, str(path))


def _read_metadata(model, where: str, spec_toml: str | Path | None,
                   role: str | None) -> tuple[SwarmSpec, Role, str]:
    props = {p.key: p.value for p in model.metadata_props}
    if spec_toml is not None:
        try:
            spec = SwarmSpec.from_toml(spec_toml)
        except SpecError as exc:
            raise ModelMetadataError(f"--spec-toml {spec_toml}: {exc}") from None
    else:
        if "spec_json" not in props:
            raise ModelMetadataError(
                f"{where} has no 'spec_json' metadata, so the observation layout is unknown: re-export it with "
                f"`swarm-export onnx`, or pass --spec-toml PATH (and --role) to say which spec it was trained with")
        try:
            spec = SwarmSpec.from_dict(json.loads(props["spec_json"]))
        except (json.JSONDecodeError, SpecError) as exc:
            raise ModelMetadataError(f"{where}: metadata 'spec_json' is not a valid spec ({exc}): re-export it "
                                     f"with `swarm-export onnx`") from None
        stored = props.get("spec_hash")
        if stored is None:
            raise ModelMetadataError(f"{where} has 'spec_json' but no 'spec_hash' metadata: re-export it with "
                                     f"`swarm-export onnx`")
        if stored != spec.hash:
            raise ModelMetadataError(
                f"{where}: metadata 'spec_hash' is {stored} but its 'spec_json' hashes to {spec.hash} (the spec "
                f"format changed, or the file was edited): re-export it with `swarm-export onnx`")
    role_name = role if role is not None else props.get("role")
    if role_name is None:
        raise ModelMetadataError(f"{where} has no 'role' metadata: re-export it with `swarm-export onnx` or pass "
                                 f"--role pursuer|scout|evader")
    try:
        role_v = Role.parse(role_name)
    except SpecError as exc:
        raise ModelMetadataError(f"{where}: {exc}") from None
    return spec, role_v, props.get("agent_id", role_v.label)


def extract_layers(model, where: str = "model") -> list[Dense]:
    """``runtime.mlp_graph.extract_layers`` with this package's errors and fix."""
    try:
        return graph.extract_layers(model, where)
    except graph.UnsupportedGraph as exc:
        raise UnsupportedGraph(f"{exc}; the C generator translates only such a chain") from None
    except graph.GraphShapeError as exc:
        raise ModelShapeError(str(exc)) from None
