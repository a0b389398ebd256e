"""ONNX actor inference for one drone: small, predictable, and never the reason a control loop crashes.

``OnnxPolicy(path)`` loads one exported actor (``firmware_export.onnx_export``) and checks it against the
spec this runtime builds observations for: a missing or damaged file, a different spec hash or role, or a
wrong input or output shape each raise a named ``PolicyError`` that says what was expected and how to fix
it. ``load_models(folder)`` reads a whole ``manifest.json`` folder (spec from the manifest, every file's
sha256 checked).

Inference is tuned for a 45-input MLP: one intra-op thread, no spinning threads, sequential execution, and
an IOBinding over input and output buffers allocated once, so ``act`` allocates nothing. A NaN or inf in an
observation, or in the network's output, never leaves the policy: the safe action (zero velocity) is
returned and ``faults`` goes up.

A model that has not run for a control period runs several times slower (its weights and onnxruntime's
code have left the caches); ``warm()`` runs it once on the last observation so that an agent can pay that
cost just before its tick instead of after it.

Two engines run the actor (``engine=``):

- ``"onnxruntime"`` (default): the session above; the observation and action checks around it are compiled
  (``runtime.kernels``), so ``act`` is one onnxruntime call plus two short compiled calls.
- ``"compiled"``: the actor's chain of ``Gemm`` (or ``MatMul`` + ``Add``), ``Relu`` and ``Tanh`` is read from
  the very same ONNX file and run by one compiled function (``runtime.kernels.mlp_act``), several times faster than any onnxruntime call for a
  model this small. It is proved against onnxruntime on the loaded model before use (max |difference| <=
  ``COMPILED_PARITY_TOL`` on random observations, else ``EngineMismatch``); a graph that is not such a chain
  raises ``EngineUnsupported`` (use the default engine for it).
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from runtime import kernels, mlp_graph
from runtime.avoidance import Avoidance
from runtime.spec import ENGINES, Role, SpecError, SwarmSpec

log = logging.getLogger(__name__)

INPUT_NAME = "obs"
OUTPUT_NAME = "action"
MANIFEST = "manifest.json"
MANIFEST_FORMAT = 1
_F32_MAX_SQ = kernels.OBS_LIMIT_SQ  # |x| beyond ~float32 max / 8 would overflow on its way through
COMPILED_PARITY_TOL = 1e-5
_FIX = "re-export with `swarm-export onnx --run runs/NAME --out models/NAME`"


class PolicyError(ValueError):
    """A model cannot be used by this runtime. The message says what was expected and how to fix it."""


class ModelNotFound(PolicyError):
    """The model file or models folder does not exist."""


class ModelCorrupted(PolicyError):
    """The file is not a loadable ONNX model, or its checksum differs from the manifest's."""


class ModelMetadataError(PolicyError):
    """The model or manifest lacks the spec metadata written by ``swarm-export onnx``."""


class SpecMismatch(PolicyError):
    """The model was exported for another spec (hash) or another role than this runtime expects."""


class ModelShapeError(PolicyError):
    """The model's input or output is not ``obs [batch, obs_dim]`` -> ``action [batch, 2]``."""


class EngineUnsupported(PolicyError):
    """``engine="compiled"`` runs only a chain of Gemm layers with Relu/Tanh; this model is something else."""


class EngineMismatch(PolicyError):
    """The compiled engine's actions differ from onnxruntime's on this model beyond the tolerance."""


def session_options(tuned: bool = True) -> ort.SessionOptions:
    """onnxruntime options for a tiny model on a busy CPU (``tuned=False``: the library's defaults)."""
    opts = ort.SessionOptions()
    if tuned:
        opts.intra_op_num_threads = 1
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        # spinning workers would burn the cores the other drones' loops need
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return opts


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class OnnxPolicy:
    """One exported actor.

    >>> pol = OnnxPolicy("models/role_based/pursuer_0.onnx", spec=spec)   # doctest: +SKIP
    >>> a = pol.act(obs)            # obs [obs_dim] -> action [2] in [-1, 1]
    >>> pol.act(obs, out=cmd)       # allocation-free: writes into cmd
    >>> A = pol.act_batch(obs_b)    # [B, obs_dim] -> [B, 2]
    """

    def __init__(self, path: str | Path, spec: SwarmSpec | None = None, role: Role | str | None = None,
                 agent_id: str | None = None, sha256: str | None = None, tuned: bool = True,
                 engine: str = "onnxruntime") -> None:
        if engine not in ENGINES:
            raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
        self.engine = engine
        self.path = Path(path)
        if not self.path.is_file():
            raise ModelNotFound(f"no ONNX model at {str(self.path)!r}: {_FIX}")
        if sha256 is not None:
            got = _sha256(self.path)
            if got != sha256:
                raise ModelCorrupted(f"{str(self.path)!r} has sha256 {got[:12]}..., the manifest says "
                                     f"{sha256[:12]}...: the file was damaged or replaced; {_FIX}")
        try:
            self.session = ort.InferenceSession(str(self.path), session_options(tuned),
                                                providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises several unrelated types for a bad file
            raise ModelCorrupted(f"{str(self.path)!r} is not a loadable ONNX model ({type(exc).__name__}: "
                                 f"{str(exc).splitlines()[0] if str(exc) else ''}); {_FIX}") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        self.metadata: dict[str, str] = dict(meta)
        self.spec, self.role, self.agent_id = self._check_metadata(spec, role, agent_id)
        self.obs_dim = self.spec.obs_dim(self.role)
        self.act_dim = self.spec.act_dim
        self._check_shapes()
        self.faults = 0
        """Observations or outputs that were not finite; each returned the safe action instead."""
        self.last_fault = ""
        self.calls = 0
        self._in1 = np.zeros((1, self.obs_dim), dtype=np.float32)
        self._out1 = np.zeros((1, self.act_dim), dtype=np.float32)
        self._io1 = self._bind(self._in1, self._out1)
        self._in_row, self._out_row = self._in1[0], self._out1[0]  # what the compiled checks read and write
        self._batch: dict[int, tuple[np.ndarray, np.ndarray, Any]] = {}
        # the C++ session and binding behind the Python wrappers: one Python frame less per call
        sess, io = getattr(self.session, "_sess", None), getattr(self._io1, "_iobinding", None)
        if sess is not None and io is not None and hasattr(sess, "run_with_iobinding"):
            self._run1 = lambda: sess.run_with_iobinding(io, None)
        else:  # another onnxruntime layout: the public call
            self._run1 = lambda: self.session.run_with_iobinding(self._io1)
        self._last_obs = np.zeros(self.obs_dim, dtype=np.float32)
        self._warm_out = np.zeros(self.act_dim, dtype=np.float32)
        self.avoidance = Avoidance(self.spec, self.role) if self.spec.avoidance.enabled else None
        """The spec's avoidance layer (``runtime.avoidance``), applied to every action; None when it is off."""
        if engine == "compiled":
            self._params, self._layers = _extract_mlp(self.path, self.obs_dim, self.act_dim)
            self._h = np.zeros((2, int(max(self._layers[:, 1].max(), self.obs_dim))), dtype=np.float32)
            self._check_compiled()

    # ------------------------------------------------------------------------------------- loading
    def _check_compiled(self) -> None:
        rng = np.random.default_rng(0)
        x = np.concatenate([rng.uniform(-1.0, 1.0, (256, self.obs_dim)), rng.normal(0.0, 3.0, (256, self.obs_dim)),
                            np.zeros((1, self.obs_dim))]).astype(np.float32)
        ref = self.session.run(None, {INPUT_NAME: x})[0]
        got = np.empty_like(ref)
        status = np.empty(len(x), dtype=np.int8)
        kernels.mlp_act_batch(x, self._params, self._layers, self._h, got, status)
        # a refused non-finite output (a NaN weight, say) agrees when onnxruntime's is not finite either
        refused = status == kernels.BAD_OUT
        got[refused] = np.where(np.isfinite(ref[refused]).all(axis=1, keepdims=True), np.nan, ref[refused])
        err = float(np.max(np.abs(np.nan_to_num(got, nan=9.0) - np.nan_to_num(ref, nan=9.0))))
        if not err <= COMPILED_PARITY_TOL:
            raise EngineMismatch(f"{str(self.path)!r}: the compiled engine differs from onnxruntime by {err:.3g} "
                                 f"(tolerance {COMPILED_PARITY_TOL}) on this model: load it with "
                                 f"engine='onnxruntime'")
        self.compiled_parity = err
        """Max |compiled - onnxruntime| measured at load."""

    def _check_metadata(self, spec: SwarmSpec | None, role: Role | str | None,
                        agent_id: str | None) -> tuple[SwarmSpec, Role, str]:
        where = str(self.path)
        missing = [k for k in ("spec_hash", "role", "agent_id", "spec_json") if k not in self.metadata]
        if missing:
            raise ModelMetadataError(f"{where!r} carries no {missing[0]!r} metadata (needs spec_hash, role, "
                                     f"agent_id, spec_json): it was not written by swarm-export onnx; {_FIX}")
        model_hash = self.metadata["spec_hash"]
        try:
            model_spec = SwarmSpec.from_dict(json.loads(self.metadata["spec_json"]))
            model_role = Role.parse(self.metadata["role"])
        except (SpecError, json.JSONDecodeError) as exc:
            raise ModelMetadataError(f"{where!r}: unreadable spec metadata ({exc}); {_FIX}") from None
        if model_spec.hash != model_hash:
            raise ModelMetadataError(f"{where!r}: its spec_json hashes to {model_spec.hash}, its spec_hash says "
                                     f"{model_hash}: the metadata was edited or written by another version; {_FIX}")
        if spec is not None and spec.hash != model_hash:
            raise SpecMismatch(
                f"{where!r} was exported for spec {model_hash} (a {model_role.label} observes "
                f"{model_spec.obs_dim(model_role)} floats), this runtime builds spec {spec.hash} "
                f"({spec.obs_dim(model_role)} floats): use models trained on this spec, or run with the models' "
                f"own spec (load_models reads it from manifest.json)")
        if role is not None:
            want = Role.parse(role) if isinstance(role, str) else Role(role)
            if want is not model_role:
                raise SpecMismatch(f"{where!r} is a {model_role.label} actor, this drone flies as a "
                                   f"{want.label}: check the manifest's agent order or the role assignment")
        mid = self.metadata["agent_id"]
        if agent_id is not None and agent_id != mid:
            raise SpecMismatch(f"{where!r} is the actor of {mid!r}, expected {agent_id!r}: check manifest.json")
        return (spec or model_spec), model_role, mid

    def _check_shapes(self) -> None:
        ins, outs = self.session.get_inputs(), self.session.get_outputs()
        want_in = f"one input {INPUT_NAME!r} [batch, {self.obs_dim}] float32"
        if len(ins) != 1 or ins[0].name != INPUT_NAME or len(ins[0].shape) != 2 or ins[0].shape[1] != self.obs_dim \
                or ins[0].type != "tensor(float)":
            got = [(i.name, i.shape, i.type) for i in ins]
            raise ModelShapeError(f"{str(self.path)!r} has inputs {got}, this runtime feeds {want_in} (the "
                                  f"{self.role.label} layout of spec {self.spec.hash}); {_FIX}")
        if len(outs) != 1 or outs[0].name != OUTPUT_NAME or len(outs[0].shape) != 2 \
                or outs[0].shape[1] != self.act_dim or outs[0].type != "tensor(float)":
            got = [(o.name, o.shape, o.type) for o in outs]
            raise ModelShapeError(f"{str(self.path)!r} has outputs {got}, this runtime expects one output "
                                  f"{OUTPUT_NAME!r} [batch, {self.act_dim}] float32; {_FIX}")

    def _bind(self, x: np.ndarray, y: np.ndarray) -> Any:
        io = self.session.io_binding()
        # OrtValues over the numpy buffers: onnxruntime reads and writes them in place, no copies per call
        io.bind_ortvalue_input(INPUT_NAME, ort.OrtValue.ortvalue_from_numpy(x))
        io.bind_ortvalue_output(OUTPUT_NAME, ort.OrtValue.ortvalue_from_numpy(y))
        return io

    # ----------------------------------------------------------------------------------- inference
    def _fault(self, what: str, n: int = 1) -> None:
        self.faults += n
        self.last_fault = what
        if self.faults == n or self.faults % 1000 < n:
            log.warning("%s: %s; returned the safe action (faults so far: %d)", self.agent_id, what, self.faults)

    def act(self, obs: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """The action ``[act_dim]`` in [-1, 1] for one observation ``[obs_dim]``; written into ``out`` when
        given (then nothing is allocated), else returned as a new float32 array."""
        o = obs if isinstance(obs, np.ndarray) else np.asarray(obs, dtype=np.float64)
        if o.shape != (self.obs_dim,):
            raise ValueError(f"{self.agent_id}: observation must have shape ({self.obs_dim},), got {o.shape}")
        if out is None:
            out = np.zeros(self.act_dim, dtype=np.float32)
        self.calls += 1
        if self.engine == "compiled":
            s = kernels.mlp_act(o, self._params, self._layers, self._h, out)
            if s == kernels.OK:
                self._last_obs = o
            else:
                self._fault("non-finite or out-of-range observation" if s == kernels.BAD_OBS
                            else "non-finite network output")
                return out
        else:
            if not kernels.load_obs(o, self._in_row):
                self._fault("non-finite or out-of-range observation")
                out[:] = 0.0
                return out
            self._run1()
            if not kernels.store_action(self._out_row, out):
                self._fault("non-finite network output")
                return out
        if self.avoidance is not None:
            self.avoidance.apply(o, out)
        return out

    def warm(self) -> None:
        """Run the network once on the last observation (result discarded) to bring its weights and code
        back into the caches before a time-critical call."""
        if self.engine == "compiled":
            kernels.mlp_act(self._last_obs, self._params, self._layers, self._h, self._warm_out)
        else:
            self._run1()

    def act_batch(self, obs: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Actions ``[B, act_dim]`` for observations ``[B, obs_dim]``; rows whose observation or output is
        not finite get the safe action and count as faults. Buffers are allocated once per batch size."""
        o = np.asarray(obs)
        if o.ndim != 2 or o.shape[1] != self.obs_dim:
            raise ValueError(f"{self.agent_id}: observations must have shape (B, {self.obs_dim}), got {o.shape}")
        b = o.shape[0]
        if self.engine == "compiled":
            if out is None:
                out = np.empty((b, self.act_dim), dtype=np.float32)
            status = np.empty(b, dtype=np.int8)
            self.calls += b
            if kernels.mlp_act_batch(o, self._params, self._layers, self._h, out, status):
                bad_obs, bad_out = int((status == kernels.BAD_OBS).sum()), int((status == kernels.BAD_OUT).sum())
                if bad_obs:
                    self._fault("non-finite or out-of-range observation", bad_obs)
                if bad_out:
                    self._fault("non-finite network output", bad_out)
            if self.avoidance is not None:
                self.avoidance.apply(np.ascontiguousarray(o), out)
            return out
        if b not in self._batch:
            x = np.zeros((b, self.obs_dim), dtype=np.float32)
            y = np.zeros((b, self.act_dim), dtype=np.float32)
            self._batch[b] = (x, y, self._bind(x, y))
        x, y, io = self._batch[b]
        self.calls += b
        with np.errstate(over="ignore", invalid="ignore"):
            x[:] = o
        good = np.isfinite(x).all(axis=1)
        if not good.all():
            self._fault("non-finite or out-of-range observation", int((~good).sum()))
            x[~good] = 0.0
        self.session.run_with_iobinding(io)
        ok = np.isfinite(y).all(axis=1)
        bad_out = good & ~ok
        if bad_out.any():
            self._fault("non-finite network output", int(bad_out.sum()))
        keep = good & ok
        if out is None:
            out = np.empty((b, self.act_dim), dtype=np.float32)
        out[:] = np.where(keep[:, None], y, 0.0)
        if self.avoidance is not None:
            self.avoidance.apply(np.ascontiguousarray(o), out)
        return out


def _extract_mlp(path: Path, obs_dim: int, act_dim: int) -> tuple[np.ndarray, np.ndarray]:
    """The flat float32 parameters and the layer table of ``runtime.kernels.mlp_act`` for a model whose graph
    is a chain ``runtime.mlp_graph`` reads (``obs -> Gemm (or MatMul + Add) [-> Relu|Tanh] -> ... -> action``);
    ``EngineUnsupported`` for anything else."""
    try:
        import onnx
    except ImportError:  # pragma: no cover - onnx is a dependency
        raise EngineUnsupported("engine='compiled' reads the weights with the onnx package: pip install onnx") \
            from None
    where = str(path)
    fix = (f"engine='compiled' runs only Gemm (or MatMul + Add) layers with Relu or Tanh between {INPUT_NAME!r} "
           f"and {OUTPUT_NAME!r}: use engine='onnxruntime'")
    try:
        layers = mlp_graph.extract_layers(onnx.load(where), repr(where))
    except mlp_graph.GraphError as exc:
        raise EngineUnsupported(f"{exc}; {fix}") from None
    if layers[0].n_in != obs_dim or layers[-1].n_out != act_dim:
        raise EngineUnsupported(f"{where!r}: the chain takes {layers[0].n_in} and ends with {layers[-1].n_out} "
                                f"values, the model's input and output have {obs_dim} and {act_dim}; {fix}")
    acts = {"none": kernels.ACT_NONE, "relu": kernels.ACT_RELU, "tanh": kernels.ACT_TANH}
    blocks: list[np.ndarray] = []
    rows: list[tuple[int, int, int, int, int]] = []
    offset = 0
    for d in layers:  # the kernel reads weights input-major: [in, out]
        rows.append((d.n_in, d.n_out, offset, offset + d.weight.size, acts[d.activation]))
        blocks += [np.ascontiguousarray(d.weight.T, dtype=np.float32).ravel(), d.bias.astype(np.float32)]
        offset += d.weight.size + d.n_out
    return np.concatenate(blocks), np.asarray(rows, dtype=np.int64)


# ------------------------------------------------------------------------------------------------
# a models folder


@dataclass(frozen=True)
class ModelEntry:
    id: str
    role: Role
    file: Path
    sha256: str
    obs_dim: int


@dataclass(frozen=True)
class Manifest:
    folder: Path
    spec: SwarmSpec
    agents: tuple[ModelEntry, ...]
    config: Any
    evaluation: Any


def read_manifest(folder: str | Path, spec: SwarmSpec | None = None) -> Manifest:
    """The models folder's ``manifest.json``, checked: its spec hashes to its ``spec_hash`` and (when given)
    equals ``spec``; the agents are the spec's agents in order."""
    d = Path(folder)
    p = d / MANIFEST
    if not d.is_dir():
        raise ModelNotFound(f"models folder {str(d)!r} does not exist: export a trained run with "
                            f"`swarm-export onnx --run runs/NAME --out {d}`")
    if not p.is_file():
        raise ModelNotFound(f"{str(d)!r} has no {MANIFEST}: it is not an exported models folder; export with "
                            f"`swarm-export onnx --run runs/NAME --out {d}`")
    try:
        doc = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelCorrupted(f"{str(p)!r} is not valid JSON ({exc}); {_FIX}") from None
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT:
        raise ModelMetadataError(f"{str(p)!r} is not a manifest of format {MANIFEST_FORMAT}; {_FIX}")
    try:
        mspec = SwarmSpec.from_dict(doc["spec"])
        agents = tuple(ModelEntry(a["id"], Role.parse(a["role"]), d / a["file"], a["sha256"], int(a["obs_dim"]))
                       for a in doc["agents"])
    except (KeyError, TypeError, ValueError) as exc:  # SpecError is a ValueError
        raise ModelMetadataError(f"{str(p)!r}: missing or invalid entry ({exc}); {_FIX}") from None
    if mspec.hash != doc.get("spec_hash"):
        raise ModelMetadataError(f"{str(p)!r}: its spec hashes to {mspec.hash}, its spec_hash says "
                                 f"{doc.get('spec_hash')}: the manifest was edited; {_FIX}")
    if spec is not None and spec.hash != mspec.hash:
        raise SpecMismatch(f"models in {str(d)!r} were exported for spec {mspec.hash}, this runtime uses spec "
                           f"{spec.hash}: run with the models' spec or export models trained on this one")
    ids = mspec.team.agent_ids()
    if tuple(a.id for a in agents) != ids or tuple(a.role for a in agents) != mspec.roles:
        raise ModelMetadataError(f"{str(p)!r} lists agents {[a.id for a in agents]}, its spec has {list(ids)} in "
                                 f"that order; {_FIX}")
    return Manifest(d, spec or mspec, agents, doc.get("config"), doc.get("evaluation"))


def load_models(folder: str | Path, spec: SwarmSpec | None = None, tuned: bool = True,
                agents: list[int] | None = None, engine: str = "onnxruntime") -> tuple[Manifest, list[OnnxPolicy]]:
    """Every actor of a models folder (or only the ``agents`` indices), checked against the manifest."""
    m = read_manifest(folder, spec)
    idx = range(len(m.agents)) if agents is None else agents
    pols = []
    for i in idx:
        e = m.agents[i]
        pol = OnnxPolicy(e.file, spec=m.spec, role=e.role, agent_id=e.id, sha256=e.sha256, tuned=tuned,
                         engine=engine)
        if pol.obs_dim != e.obs_dim:
            raise ModelShapeError(f"{str(e.file)!r} takes {pol.obs_dim} inputs, the manifest says {e.obs_dim}; "
                                  f"{_FIX}")
        pols.append(pol)
    return m, pols
