"""Compiled inner loops of ``runtime.policy``: the checks around one inference, and a whole small MLP.

Every call from Python costs a few hundred nanoseconds, so the work around an onnxruntime call is folded
into one compiled function on each side (copy the observation in with its range check; copy the action out
with its finiteness check), and the ``compiled`` engine runs the entire actor in one call.

The MLP kernel computes what an exported actor's ONNX graph computes (``Gemm`` layers, each optionally
followed by ``Relu`` or ``Tanh``), in float32 like onnxruntime, from one flat parameter buffer:
``layers[l] = (n_in, n_out, weight_offset, bias_offset, activation)`` with the weight stored ``[n_in, n_out]``
(input-major, so the inner loop over outputs is contiguous and vectorizes). ``runtime.policy`` extracts the
buffer from the model file and proves the kernel against onnxruntime on that very model before using it.

Floating point: only ``contract`` (fused multiply-add) is allowed. No ``nnan``/``ninf`` flags, so the NaN
and inf checks below are kept by the compiler, and no flush-to-zero mode is set anywhere.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

ACT_NONE, ACT_RELU, ACT_TANH = 0, 1, 2
F32_MAX = float(np.finfo(np.float32).max)
OBS_LIMIT_SQ = F32_MAX * F32_MAX / 64.0
"""An observation whose squared norm reaches this would overflow float32 on its way through the network."""

OK, BAD_OBS, BAD_OUT = 0, 1, 2


@njit(cache=True, nogil=True)
def load_obs(obs, buf):
    """``buf[:n] = obs`` (cast to buf's float32) when ``obs`` is finite and in range; else ``False``, buf as is."""
    q = 0.0
    for i in range(obs.shape[0]):
        v = float(obs[i])
        q += v * v
    if not q < OBS_LIMIT_SQ:  # NaN compares false
        return False
    for i in range(obs.shape[0]):
        buf[i] = obs[i]
    return True


@njit(cache=True, nogil=True)
def store_action(res, out):
    """``out[:] = res[:len(out)]`` when finite (``True``); else zeros, the safe action (``False``)."""
    n = out.shape[0]
    for j in range(n):
        if not math.isfinite(res[j]):
            for k in range(n):
                out[k] = 0.0
            return False
    for j in range(n):
        out[j] = res[j]
    return True


@njit(cache=True, nogil=True, fastmath={"contract"})
def mlp_act(obs, params, layers, h, out):
    """One observation through the MLP into ``out``; returns OK, BAD_OBS or BAD_OUT (then ``out`` is zero).

    ``h`` is float32 scratch ``[2, widest layer]``; nothing is allocated (slices and reshapes are views).
    Layers are written as row views of a reshaped weight block: with plain index arithmetic numba keeps
    negative-index handling in the inner loop and it does not vectorize (4.7 us against 1.3 us here).
    """
    a = h[0]
    b = h[1]
    if not load_obs(obs, a):
        out[:] = 0.0
        return BAD_OBS
    for layer in range(layers.shape[0]):
        n_in = layers[layer, 0]
        n_out = layers[layer, 1]
        w0 = layers[layer, 2]
        b0 = layers[layer, 3]
        act = layers[layer, 4]
        w = params[w0:w0 + n_in * n_out].reshape((n_in, n_out))
        dst = b[:n_out]
        dst[:] = params[b0:b0 + n_out]
        for i in range(n_in):
            xi = a[i]
            if xi != 0.0:  # after a ReLU many inputs are zero; a NaN input still propagates
                row = w[i]
                for j in range(n_out):
                    dst[j] += xi * row[j]
        if act == ACT_RELU:
            for j in range(n_out):
                if dst[j] < 0.0:  # NaN stays NaN, for the output check to catch
                    dst[j] = 0.0
        elif act == ACT_TANH:
            for j in range(n_out):
                dst[j] = math.tanh(dst[j])
        a, b = b, a
    return OK if store_action(a, out) else BAD_OUT


@njit(cache=True, nogil=True, fastmath={"contract"})
def mlp_act_batch(obs, params, layers, h, out, good):
    """``mlp_act`` row by row over ``obs [B, n]``; ``good[b]`` is its status. Returns the number of faults."""
    faults = 0
    for b in range(obs.shape[0]):
        s = mlp_act(obs[b], params, layers, h, out[b])
        good[b] = s
        if s != OK:
            faults += 1
    return faults
