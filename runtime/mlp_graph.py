"""An exported actor's ONNX graph as a plain list of dense layers: the one reader behind the runtime's compiled
engine (``runtime.policy``, ``engine="compiled"``) and the C generator (``firmware_export.mlp_graph``).

Supported: exactly the graphs ``training.networks.Actor`` exports to, a chain of ``Gemm`` (or ``MatMul`` +
``Add``) with constant weights, each optionally followed by ``Relu`` or ``Tanh``. ``Identity`` nodes are skipped
and ``Constant`` nodes are read as weights. Any other operator, a branch in the chain, or weights that are not
constants is an ``UnsupportedGraph`` error naming the node; the callers add what to do instead.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ACTIVATIONS = ("relu", "tanh", "none")


class GraphError(ValueError):
    """The graph is not a chain of dense layers this reader translates."""


class UnsupportedGraph(GraphError):
    """An operator or a structure other than Gemm / MatMul+Add, Relu, Tanh, Identity in one chain."""


class GraphShapeError(GraphError):
    """Weights, input or output do not have the shapes of a [batch, features] MLP."""


@dataclass(frozen=True)
class Dense:
    """``y = act(weight @ x + bias)``."""

    weight: np.ndarray
    """[out, in] float32, row-major (one output neuron per row)."""
    bias: np.ndarray
    """[out] float32."""
    activation: str
    """One of ``ACTIVATIONS``."""

    @property
    def n_in(self) -> int:
        return int(self.weight.shape[1])

    @property
    def n_out(self) -> int:
        return int(self.weight.shape[0])



def extract_layers(model, where: str = "model") -> list[Dense]:
    """The graph as dense layers, input to output. Pure (reads ``model`` only)."""
    from onnx import numpy_helper

    g = model.graph
    consts = {t.name: numpy_helper.to_array(t) for t in g.initializer}
    nodes = []
    for n in g.node:
        if n.op_type == "Constant":
            consts[n.output[0]] = _constant_value(n, where)
        else:
            nodes.append(n)
    inputs = [i for i in g.input if i.name not in consts]
    if len(inputs) != 1 or len(g.output) != 1:
        raise UnsupportedGraph(f"{where}: the actor must have one input and one output, it has "
                               f"{[i.name for i in inputs]} -> {[o.name for o in g.output]}: export a "
                               f"training.networks.Actor with `swarm-export onnx`")
    _check_io_shape(inputs[0], where, "input")
    _check_io_shape(g.output[0], where, "output")
    consumers: dict[str, list] = {}
    for n in nodes:
        for name in n.input:
            consumers.setdefault(name, []).append(n)
    layers: list[Dense] = []
    cur = inputs[0].name
    pending: tuple[np.ndarray, np.ndarray] | None = None  # a Dense waiting for its activation
    while cur != g.output[0].name:
        users = consumers.get(cur, [])
        if len(users) != 1:
            raise UnsupportedGraph(f"{where}: tensor {cur!r} feeds {len(users)} nodes; only a "
                                   f"single chain of Gemm/MatMul+Add, Relu and Tanh")
        n = users[0]
        op = n.op_type
        if op == "Identity":
            cur = n.output[0]
            continue
        if op in ("Gemm", "MatMul"):
            if pending is not None:
                layers.append(Dense(*pending, "none"))
            pending, cur = _dense(n, cur, consts, consumers, where)
            continue
        if op in ("Relu", "Tanh"):
            if pending is None:
                raise UnsupportedGraph(f"{where}: node {n.name or op!r} ({op}) does not follow a Gemm or MatMul+Add: "
                                       f"each activation belongs to the layer before it")
            layers.append(Dense(*pending, op.lower()))
            pending, cur = None, n.output[0]
            continue
        raise UnsupportedGraph(f"{where}: operator {op} (node {n.name!r}) is not supported: an actor is a chain of "
                               f"Gemm, MatMul+Add, Relu, Tanh (and Identity): export a training.networks.Actor, or "
                               f"extend runtime/mlp_graph.py")
    if pending is not None:
        layers.append(Dense(*pending, "none"))
    if not layers:
        raise UnsupportedGraph(f"{where}: the graph has no Gemm or MatMul layer")
    for a, b in zip(layers, layers[1:]):
        if a.n_out != b.n_in:
            raise GraphShapeError(f"{where}: a layer outputs {a.n_out} values but the next takes {b.n_in}")
    return layers


def _constant_value(node, where: str) -> np.ndarray:
    from onnx import numpy_helper

    for a in node.attribute:
        if a.name == "value":
            return numpy_helper.to_array(a.t)
    raise UnsupportedGraph(f"{where}: Constant node {node.name!r} has no tensor 'value' "
                           f"({[a.name for a in node.attribute]}): re-export the model")


def _check_io_shape(vi, where: str, what: str) -> None:
    dims = vi.type.tensor_type.shape.dim
    if len(dims) != 2:
        raise GraphShapeError(f"{where}: the {what} {vi.name!r} has rank {len(dims)}, expected [batch, features]: "
                              f"export the actor with a batch dimension")
    if vi.type.tensor_type.elem_type != 1:  # onnx.TensorProto.FLOAT
        raise GraphShapeError(f"{where}: the {what} {vi.name!r} is not float32: export the actor in float32")


def _attrs(node) -> dict:
    from onnx import helper

    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def _dense(node, cur: str, consts: dict, consumers: dict, where: str):
    """(weight [out, in], bias [out]) of a Gemm, or of a MatMul and the Add after it; and the output tensor."""
    name = node.name or node.op_type
    if node.input[0] != cur or any(i not in consts for i in node.input[1:] if i):
        raise UnsupportedGraph(f"{where}: {node.op_type} node {name!r} must take the activations as its first input "
                               f"and constant weights: re-export the model with constant folding")
    w = np.asarray(consts[node.input[1]], dtype=np.float64)
    if w.ndim != 2:
        raise GraphShapeError(f"{where}: {node.op_type} node {name!r} has a weight of shape {w.shape}, expected 2-D")
    if node.op_type == "Gemm":
        at = _attrs(node)
        if at.get("transA", 0):
            raise UnsupportedGraph(f"{where}: Gemm node {name!r} has transA=1: re-export the model")
        w = w if at.get("transB", 0) else w.T  # now [out, in]
        w = w * at.get("alpha", 1.0)
        b = consts[node.input[2]] if len(node.input) > 2 and node.input[2] else np.zeros(w.shape[0])
        b = np.broadcast_to(np.asarray(b, dtype=np.float64).reshape(-1), (w.shape[0],)) * at.get("beta", 1.0)
        return (w.astype(np.float32), b.astype(np.float32)), node.output[0]
    w = w.T  # MatMul: x [B, in] @ W [in, out]
    out = node.output[0]
    users = consumers.get(out, [])
    if len(users) == 1 and users[0].op_type == "Add":
        add = users[0]
        other = [i for i in add.input if i != out]
        if len(other) != 1 or other[0] not in consts:
            raise UnsupportedGraph(f"{where}: Add node {add.name!r} after MatMul {name!r} must add a constant bias")
        b = np.asarray(consts[other[0]], dtype=np.float64)
        if b.size != w.shape[0]:
            raise GraphShapeError(f"{where}: Add node {add.name!r} adds {b.shape} to {w.shape[0]} outputs")
        return (w.astype(np.float32), b.reshape(-1).astype(np.float32)), add.output[0]
    return (w.astype(np.float32), np.zeros(w.shape[0], np.float32)), out
