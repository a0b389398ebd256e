"""C text of the int8 layers (``--quant int8w``): int8 weights times q15 inputs with SXTB16/SMLAD on the
Cortex-M4 (the CMSIS-NN q7 x q15 way), a portable C twin of the same integer arithmetic for other targets, and
the packing of the weights into the words the kernel reads. ``firmware_export.cgen`` assembles them into
``policy.c``; ``firmware_export.quantize.int8_forward`` is the numpy reference of the arithmetic."""
from __future__ import annotations

import numpy as np

from firmware_export.quantize import Q15_MAX

QGROUP = 4
"""int8 layers: output neurons per group (4 accumulators, 2 packed inputs, 2 weight words, a temporary and three
loop registers: 12 of the 14 allocatable core registers)."""
QBLOCK = 16
"""int8 layers: inputs are zero-padded to a multiple of this (the SMLAD loop handles 16 inputs per iteration)."""

INT8_MAX_INPUTS = 512
"""Largest int8 layer input: ``512 * 127 * 32767 < 2**31``, so the int32 accumulator cannot overflow."""


def _pad(n: int, to: int) -> int:
    return -(-n // to) * to


def _store(k: int, v: str, activation: str) -> list[str]:
    """``y[k] = act(v)`` (``v`` in accumulator ``a<k>`` when it is already there)."""
    a = f"a{k}"
    if activation == "relu":
        if v == a:
            return [f"        y[{k}] = {a} > 0.0f ? {a} : 0.0f;"]
        return ["        {", f"            const float z = {v};", f"            y[{k}] = z > 0.0f ? z : 0.0f;", "        }"]
    if activation == "tanh":
        return [f"        y[{k}] = swp_tanhf({v});"]
    return [f"        y[{k}] = {v};"]


_Q15_TEXT = f"""/* q15 copy of x[0..n) with one scale for the vector (x ~= q * scale, |q| <= {Q15_MAX}), packed two per word
 * (x[2k] in the low half), zero-padded to n_pad; returns the scale. The M4 rounds with VCVTR (to nearest,
 * ties to even), the portable C to nearest with ties away from zero: they differ only on exact ties. */
#ifdef SWP_M4_ASM
static int32_t swp_round(float v) {{ int32_t r; __asm__("vcvtr.s32.f32 %1, %1\\n\\tvmov %0, %1" : "=r" (r), "+t" (v)); return r; }}
#else
static int32_t swp_round(float v) {{ return (int32_t)(v >= 0.0f ? v + 0.5f : v - 0.5f); }}
#endif
static uint32_t swp_pack(int32_t lo, int32_t hi) {{ return ((uint32_t)lo & 0xffffu) | ((uint32_t)hi << 16); }}
static float swp_q15(const float *restrict x, int n, int n_pad, uint32_t *restrict xq)
{{
    float amax = 0.0f, inv;
    int i = 0;
#ifdef SWP_M4_ASM
    if (n >= 4) {{ /* max |x| on the bit patterns: for finite floats 2*bits orders like |x| (LDRD, LSL, CMP, IT) */
        const float *xp = x;
        uint32_t m = 0u, v0, v1, v2, v3;
        int k = n >> 2;
        __asm__ volatile(
            "1:\\n\\t"
            "ldrd %[v0], %[v1], [%[xp]], #8\\n\\t" "ldrd %[v2], %[v3], [%[xp]], #8\\n\\t"
            "lsls %[v0], %[v0], #1\\n\\t" "cmp %[v0], %[m]\\n\\t" "it hi\\n\\t" "movhi %[m], %[v0]\\n\\t"
            "lsls %[v1], %[v1], #1\\n\\t" "cmp %[v1], %[m]\\n\\t" "it hi\\n\\t" "movhi %[m], %[v1]\\n\\t"
            "lsls %[v2], %[v2], #1\\n\\t" "cmp %[v2], %[m]\\n\\t" "it hi\\n\\t" "movhi %[m], %[v2]\\n\\t"
            "lsls %[v3], %[v3], #1\\n\\t" "cmp %[v3], %[m]\\n\\t" "it hi\\n\\t" "movhi %[m], %[v3]\\n\\t"
            "subs %[k], %[k], #1\\n\\t"
            "bne 1b\\n\\t"
            : [xp] "+r" (xp), [k] "+r" (k), [m] "+r" (m), [v0] "=&r" (v0), [v1] "=&r" (v1), [v2] "=&r" (v2),
              [v3] "=&r" (v3)
            :
            : "cc", "memory");
        m >>= 1;
        __asm__("vmov %0, %1" : "=t" (amax) : "r" (m));
        i = n & ~3;
    }}
#endif
    for (; i < n; ++i) {{
        const float a = x[i] < 0.0f ? -x[i] : x[i];
        amax = a > amax ? a : amax;
    }}
    if (!(amax > 0.0f)) amax = 1.0f; /* an all-zero input: any scale gives zeros */
    inv = {Q15_MAX}.0f / amax;
    i = 0;
#ifdef SWP_M4_ASM
    if (n >= 4) {{ /* 4 inputs per iteration: VLDM, VMUL, VCVTR, VMOV to core registers, PKHBT, STRD (30 cycles) */
        const float *xp = x;
        uint32_t *qp = xq, q0, q1, q2, q3;
        int k = n >> 2;
        __asm__ volatile(
            "1:\\n\\t"
            "vldmia %[xp]!, {{s12-s15}}\\n\\t"
            "vmul.f32 s12, s12, %[inv]\\n\\t" "vmul.f32 s13, s13, %[inv]\\n\\t"
            "vmul.f32 s14, s14, %[inv]\\n\\t" "vmul.f32 s15, s15, %[inv]\\n\\t"
            "vcvtr.s32.f32 s12, s12\\n\\t" "vcvtr.s32.f32 s13, s13\\n\\t"
            "vcvtr.s32.f32 s14, s14\\n\\t" "vcvtr.s32.f32 s15, s15\\n\\t"
            "vmov %[q0], %[q1], s12, s13\\n\\t" "vmov %[q2], %[q3], s14, s15\\n\\t"
            "pkhbt %[q0], %[q0], %[q1], lsl #16\\n\\t" "pkhbt %[q2], %[q2], %[q3], lsl #16\\n\\t"
            "strd %[q0], %[q2], [%[qp]], #8\\n\\t"
            "subs %[k], %[k], #1\\n\\t"
            "bne 1b\\n\\t"
            : [xp] "+r" (xp), [qp] "+r" (qp), [k] "+r" (k), [q0] "=&r" (q0), [q1] "=&r" (q1), [q2] "=&r" (q2),
              [q3] "=&r" (q3)
            : [inv] "t" (inv)
            : "s12", "s13", "s14", "s15", "cc", "memory");
        i = n & ~3;
    }}
#endif
    for (; i + 1 < n; i += 2) xq[i >> 1] = swp_pack(swp_round(x[i] * inv), swp_round(x[i + 1] * inv));
    if (i < n) {{
        xq[i >> 1] = swp_pack(swp_round(x[i] * inv), 0);
        i += 2;
    }}
    for (; i < n_pad; i += 2) xq[i >> 1] = 0u;
    return amax / {Q15_MAX}.0f;
}}

#ifndef SWP_M4_ASM
/* What SXTB16/SMLAD compute, in portable C: four int8 weights packed w0 w2 w1 w3 times (x0, x1), (x2, x3). */
static int32_t swp_s8(uint32_t v, int sh) {{ const int32_t b = (int32_t)((v >> sh) & 0xffu); return b - ((b & 0x80) << 1); }}
static int32_t swp_s16(uint32_t v, int sh) {{ const int32_t h = (int32_t)((v >> sh) & 0xffffu); return h - ((h & 0x8000) << 1); }}
static int32_t swp_dot4(uint32_t w, uint32_t x01, uint32_t x23)
{{
    return swp_s8(w, 0) * swp_s16(x01, 0) + swp_s8(w, 16) * swp_s16(x01, 16)
         + swp_s8(w, 8) * swp_s16(x23, 0) + swp_s8(w, 24) * swp_s16(x23, 16);
}}
#endif
"""


def _asm(lines: list[str], indent: str = "            ") -> list[str]:
    return [f'{indent}"{x}\\n\\t"' for x in lines]


def _m4_smlad_loop() -> list[str]:
    """The int8 inner loop in Thumb-2 DSP instructions, 16 inputs x 4 neurons per iteration: per 4 inputs one
    LDRD of two packed q15 input pairs (3 cycles), one LDM of the 4 neurons' weight words (5), 8 SXTB16 and 8 SMLAD
    (16): 24 cycles for 16 MACs in the cycle model, plus 4 per iteration for the loop. The LDM's registers are
    pinned (r8-r11, ascending as LDM needs); the rest is left to the compiler."""
    body = []
    for _ in range(QBLOCK // 4):
        body += ["ldrd %[x01], %[x23], [%[xp]], #8", "ldmia %[w]!, {%[w0], %[w1], %[w2], %[w3]}"]
        for k in range(QGROUP):
            body += [f"sxtb16 %[t], %[w{k}]", f"sxtb16 %[w{k}], %[w{k}], ror #8",
                     f"smlad %[a{k}], %[t], %[x01], %[a{k}]", f"smlad %[a{k}], %[w{k}], %[x23], %[a{k}]"]
    regs = [f'register uint32_t w{k} __asm__("r{8 + k}");' for k in range(QGROUP)]
    return (["        {", *[f"        {r}" for r in regs], "        uint32_t x01, x23, t;", f"        n /= {QBLOCK // 4};",
             "        __asm__ volatile(", *_asm(["1:", *body, "subs %[n], %[n], #1", "bne 1b"]),
             '            : [a0] "+r" (a0), [a1] "+r" (a1), [a2] "+r" (a2), [a3] "+r" (a3), [xp] "+r" (xp),',
             '              [w] "+r" (w), [n] "+r" (n), [x01] "=&r" (x01), [x23] "=&r" (x23), [t] "=&r" (t),',
             '              [w0] "=&r" (w0), [w1] "=&r" (w1), [w2] "=&r" (w2), [w3] "=&r" (w3)',
             '            :', '            : "cc", "memory");', "        }"])


def _m4_relu_epilogue() -> list[str]:
    """``y = relu(acc * (s * x_scale) + b)`` for the 4 neurons in VFP instructions (s and b are stored halved
    for relu layers, so that relu(z) = z/2 + |z/2| is exact and costs a VABS and a VADD): 43 cycles."""
    ops = [f"vmov s{8 + k}, %[a{k}]" for k in range(4)] + [f"vcvt.f32.s32 s{8 + k}, s{8 + k}" for k in range(4)]
    ops += ["vldmia %[s]!, {s12-s15}"] + [f"vmul.f32 s{12 + k}, s{12 + k}, %[xs]" for k in range(4)]
    ops += [f"vmul.f32 s{8 + k}, s{8 + k}, s{12 + k}" for k in range(4)] + ["vldmia %[b]!, {s12-s15}"]
    ops += [f"vadd.f32 s{8 + k}, s{8 + k}, s{12 + k}" for k in range(4)]
    ops += [f"vabs.f32 s{12 + k}, s{8 + k}" for k in range(4)] + [f"vadd.f32 s{8 + k}, s{8 + k}, s{12 + k}" for k in range(4)]
    ops += ["vstmia %[y]!, {s8-s11}"]
    return (["        __asm__ volatile(", *_asm(ops),
             '            : [s] "+r" (s), [b] "+r" (b), [y] "+r" (y)',
             '            : [a0] "r" (a0), [a1] "r" (a1), [a2] "r" (a2), [a3] "r" (a3), [xs] "t" (x_scale)',
             '            : ' + ", ".join(f'"s{k}"' for k in range(8, 16)) + ', "memory");'])


def _kernel_q7(activation: str) -> tuple[str, str]:
    """Name and text of the int8 kernel: ``QGROUP`` neurons per group, inputs in blocks of 4 (``n_blk``, even)."""
    name = f"swp_dense{QGROUP}_{activation}_q7"
    lines = [f"static void {name}(const uint32_t *restrict xq, int n_blk, float x_scale, const uint32_t *restrict w,",
             "    const float *restrict b, const float *restrict s, int n_groups, float *restrict y)", "{",
             "    int g;", "    for (g = 0; g < n_groups; ++g) {",
             "        int32_t " + ", ".join(f"a{k} = 0" for k in range(QGROUP)) + ";",
             "        const uint32_t *xp = xq;", "        int n = n_blk;", "#ifdef SWP_M4_ASM", *_m4_smlad_loop(),
             "#else", "        do {", "            const uint32_t x01 = xp[0], x23 = xp[1];"]
    lines += [f"            a{k} += swp_dot4(w[{k}], x01, x23);" for k in range(QGROUP)]
    lines += [f"            w += {QGROUP}; xp += 2;", "        } while (--n > 0);", "#endif"]
    if activation == "relu":  # s and b halved: y = z/2 + |z/2|
        lines += ["#ifdef SWP_M4_ASM", *_m4_relu_epilogue(), "#else"]
        for k in range(QGROUP):
            lines += ["        {", f"            const float z = (float)a{k} * (s[{k}] * x_scale) + b[{k}];",
                      f"            y[{k}] = z + (z < 0.0f ? -z : z);", "        }"]
        lines += [f"        b += {QGROUP}; s += {QGROUP}; y += {QGROUP};", "#endif"]
    else:
        for k in range(QGROUP):
            lines += _store(k, f"(float)a{k} * (s[{k}] * x_scale) + b[{k}]", activation)
        lines += [f"        b += {QGROUP}; s += {QGROUP}; y += {QGROUP};"]
    lines += ["    }", "}", ""]
    return name, "\n".join(lines)


def pack_q7(q: np.ndarray) -> np.ndarray:
    """int8 ``q`` [out, in] as the uint32 words the q7 kernel reads: rows padded to ``QGROUP``, inputs to
    ``QBLOCK`` (zeros), then for each group of rows, each block of 4 inputs, each row of the group one word with
    bytes (w0, w2, w1, w3) from the least significant up."""
    n_out, n_in = q.shape
    p = np.zeros((_pad(n_out, QGROUP), _pad(n_in, QBLOCK)), np.int64)
    p[:n_out, :n_in] = q
    u = p & 0xFF
    blk = u.reshape(p.shape[0] // QGROUP, QGROUP, -1, 4).transpose(0, 2, 1, 3)  # [group][block][row][4]
    words = blk[..., 0] | (blk[..., 2] << 8) | (blk[..., 1] << 16) | (blk[..., 3] << 24)
    return words.reshape(-1).astype(np.uint32)
