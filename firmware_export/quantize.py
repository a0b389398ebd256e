"""int8 weights for the C export (``--quant int8w``): which layers are int8, and how their weights are rounded.

Scheme (the same one ``policy.h`` states):

- hidden layers: int8 weights, one float scale per output neuron (per row, symmetric, ``scale = max|w| / 127``);
  the C takes each such layer's input as q15 (one scale per vector, ``max|x| / 32767``), accumulates
  ``q . x_q`` exactly in int32 (SMLAD on the Cortex-M4), then ``y = act(scale * x_scale * acc + bias)``
  (``int8_forward`` is that arithmetic in numpy);
- the output layer (64 -> 2, 0.5 KB as float) stays float32: on trained actors the hidden activations are
  large (tens), so rounding its 128 weights alone moves the action by up to ~0.2.

Rounding ``"gptq"`` (the default) is GPTQ-style error compensation (Frantar et al. 2023, "GPTQ: Accurate
Post-Training Quantization for Generative Pre-trained Transformers") on calibration observations: layer by layer,
input to output, the float weights are first refitted by least squares so that the layer reproduces the float
model's pre-activations *from the already-quantized layers' outputs*; then the columns are rounded one at a time
(largest input energy first) and each rounding error is spread over the not-yet-rounded columns of the same row
through the inverse of ``H = X^T X`` (X: the layer's calibration inputs); finally each bias absorbs the mean
remaining error. ``"nearest"`` is plain round-to-nearest, for comparison.

Calibration observations must not be the ones parity is measured on (``c_export`` uses other seeds).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware_export.mlp_graph import CExportError, Dense
from runtime.spec import INT8_QMAX

ROUNDINGS = ("gptq", "nearest")
QMAX = INT8_QMAX
Q15_MAX = 32767
"""q15 activations of the int8 layers (the C kernels take each layer's input as int16 with one scale per vector)."""
DAMP = 0.01
"""GPTQ's damping: ``H + DAMP * mean(diag H) * I`` (keeps the inverse sane for inputs that never vary)."""


@dataclass(frozen=True)
class QDense:
    """One layer as the C computes it: ``act(scale * (q @ x) + bias)`` for int8 (``scale`` set), else
    ``act(weight @ x + bias)`` with float32 ``weight``."""

    weight: np.ndarray
    """[out, in]: int8 when ``scale`` is set, float32 otherwise."""
    scale: np.ndarray | None
    """[out] float32 per-row scales, or None for a float layer."""
    bias: np.ndarray
    activation: str

    @property
    def is_int8(self) -> bool:
        return self.scale is not None

    def dequantized(self) -> Dense:
        """The float layer this computes (the reference its C must reproduce)."""
        if self.scale is None:
            return Dense(self.weight, self.bias, self.activation)
        return Dense(self.weight.astype(np.float64) * self.scale.astype(np.float64)[:, None], self.bias,
                     self.activation)


def float_layers(layers: tuple[Dense, ...]) -> tuple[QDense, ...]:
    return tuple(QDense(d.weight.astype(np.float32), None, d.bias.astype(np.float32), d.activation) for d in layers)


def dequantized(qlayers: tuple[QDense, ...]) -> tuple[Dense, ...]:
    return tuple(q.dequantized() for q in qlayers)


def _act(z: np.ndarray, activation: str) -> np.ndarray:
    if activation == "relu":
        return np.maximum(z, 0.0)
    if activation == "tanh":
        return np.tanh(z)
    return z


def row_scales(w: np.ndarray) -> np.ndarray:
    amax = np.abs(w).max(axis=1)
    return np.where(amax > 0, amax / QMAX, 1.0)


def round_nearest(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric per-row int8 by rounding to nearest: ``w ~= q * scale[:, None]``."""
    s = row_scales(w)
    return np.clip(np.rint(w / s[:, None]), -QMAX, QMAX).astype(np.int8), s.astype(np.float32)


def round_gptq(w: np.ndarray, x: np.ndarray, damp: float = DAMP) -> tuple[np.ndarray, np.ndarray]:
    """Per-row int8 of ``w`` [out, in] minimising ``||(w - q*s) x^T||`` over the calibration inputs ``x`` [N, in]
    column by column (GPTQ with the shared input Hessian ``x^T x``, columns in decreasing ``diag(H)``)."""
    w = np.asarray(w, dtype=np.float64)
    s = row_scales(w)
    h = x.T @ x
    diag = np.diag(h).copy()
    dead = diag <= 0
    h[dead, dead] = 1.0
    h[np.diag_indices_from(h)] += damp * float(np.mean(np.diag(h)))
    order = np.argsort(-np.diag(h), kind="stable")
    h = h[np.ix_(order, order)]
    u = np.linalg.cholesky(np.linalg.inv(h)).T  # upper Cholesky factor of H^-1
    work = w[:, order].copy()
    q = np.zeros_like(work)
    for j in range(work.shape[1]):
        q[:, j] = np.clip(np.rint(work[:, j] / s), -QMAX, QMAX)
        e = (work[:, j] - q[:, j] * s) / u[j, j]
        work[:, j + 1:] -= np.outer(e, u[j, j + 1:])
    out = np.empty_like(q)
    out[:, order] = q
    return out.astype(np.int8), s.astype(np.float32)


def quantize_layers(layers: tuple[Dense, ...], calib: np.ndarray | None, rounding: str = "gptq") -> tuple[QDense, ...]:
    """The ``int8w`` scheme of this module's docstring for ``layers``; ``calib`` [N, obs_dim] observations
    (needed for ``"gptq"``)."""
    if rounding not in ROUNDINGS:
        raise CExportError(f"unknown int8 rounding {rounding!r}: use one of {list(ROUNDINGS)}")
    if rounding == "gptq" and (calib is None or len(calib) < 4 * max(d.n_in for d in layers)):
        raise CExportError("GPTQ rounding needs calibration observations (at least 4 per weight column): pass "
                           "more --calib-obs, or use --int8-rounding nearest")
    out: list[QDense] = []
    x_f = None if calib is None else np.asarray(calib, dtype=np.float64)  # input of layer li in the float model
    x_q = x_f  # ... and in the quantized model built so far
    for li, d in enumerate(layers):
        w, b = d.weight.astype(np.float64), d.bias.astype(np.float64)
        if li == len(layers) - 1:
            out.append(QDense(d.weight.astype(np.float32), None, d.bias.astype(np.float32), d.activation))
            break
        if rounding == "nearest":
            q, s = round_nearest(w)
        else:
            z_f = x_f @ w.T + b
            if li > 0:  # refit to reproduce the float pre-activations from the quantized layers' outputs
                a = np.c_[x_q, np.ones(len(x_q))]
                sol = np.linalg.lstsq(a, z_f, rcond=None)[0]
                w, b = sol[:-1].T, sol[-1]
            q, s = round_gptq(w, x_q)
            z_q = x_q @ (q.astype(np.float64) * s.astype(np.float64)[:, None]).T + b
            b = b + (z_f - z_q).mean(axis=0)  # bias correction
            x_f = _act(z_f, d.activation)
            x_q = _act(x_q @ (q.astype(np.float64) * s.astype(np.float64)[:, None]).T + b, d.activation)
        out.append(QDense(q, s, b.astype(np.float32), d.activation))
    return tuple(out)


def q15_vector(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the C's ``swp_q15`` computes for each row of ``x`` [B, n] (float32 arithmetic): int16 values
    ``round(x * 32767 / max|x|)`` (ties away from zero) and the per-row scale ``max|x| / 32767``."""
    x = np.asarray(x, dtype=np.float32)
    amax = np.abs(x).max(axis=1)
    amax = np.where(amax > 0, amax, np.float32(1.0)).astype(np.float32)
    inv = (np.float32(Q15_MAX) / amax).astype(np.float32)
    v = (x * inv[:, None]).astype(np.float32)
    q = np.trunc(v + np.where(v >= 0, np.float32(0.5), np.float32(-0.5))).astype(np.int32)
    return q, (amax / np.float32(Q15_MAX)).astype(np.float32)


def int8_forward(qlayers: tuple[QDense, ...], obs: np.ndarray) -> np.ndarray:
    """The C's arithmetic for ``qlayers`` on ``obs`` [B, in]: int8 layers take their input as q15 (``q15_vector``),
    accumulate ``q . x_q`` exactly in integers and scale once per neuron; float layers as in float32. The
    reference the int8w C must reproduce (up to float32 rounding order)."""
    x = np.asarray(obs, dtype=np.float32)
    for ql in qlayers:
        if ql.is_int8:
            xq, xs = q15_vector(x)
            acc = xq.astype(np.int64) @ ql.weight.astype(np.int64).T
            z = acc.astype(np.float64) * (ql.scale.astype(np.float64)[None, :] * xs.astype(np.float64)[:, None])
            z = z + ql.bias.astype(np.float64)
        else:
            z = x.astype(np.float64) @ ql.weight.astype(np.float64).T + ql.bias.astype(np.float64)
        x = _act(z, ql.activation).astype(np.float32)
    return x
