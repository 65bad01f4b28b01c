"""Steps 4-5: semantic entropy and the adaptive kernel length."""
import math

import taichi as ti

from kernels.fusion import decay_factor

LN2 = math.log(2.0)


@ti.func
def fast_log(x):
    """Natural log of a positive, normal float32 to ~1e-6 relative error, without libm.

    The entropy takes 19 logs per voxel of every scan; libm's log was a large share of that
    step, while the kernel length needs nowhere near float precision. x = m * 2^e with m in
    [1, 2); ln m = 2 atanh((m - 1) / (m + 1)) as an odd series in t = (m - 1) / (m + 1) <= 1/3.
    """
    bits = ti.bit_cast(x, ti.i32)
    e = ((bits >> 23) & 0xFF) - 127
    m = ti.bit_cast((bits & 0x007FFFFF) | 0x3F800000, ti.f32)
    t = (m - 1.0) / (m + 1.0)
    t2 = t * t
    ln_m = 2.0 * t * (1.0 + t2 * (1.0 / 3.0 + t2 * (1.0 / 5.0 + t2 * (1.0 / 7.0 + t2 * (1.0 / 9.0)))))
    return ln_m + ti.cast(e, ti.f32) * LN2


@ti.func
def normalized_entropy(p, num_real: ti.template()):
    """Shannon entropy of the unnormalised vector p over classes 1..C-1, divided by log(C-1).

    Class 0 (unlabeled) never receives evidence, so it is left out of the support: a voxel
    with uniform evidence over the 19 real classes gets exactly 1.
    """
    total = 0.0
    for c in ti.static(range(1, num_real + 1)):
        total += p[c]
    h = 0.0
    for c in ti.static(range(1, num_real + 1)):
        q = p[c] / total
        if q > 1e-30:
            h -= q * fast_log(q)
    return h / ti.log(ti.cast(num_real, ti.f32))


@ti.func
def adaptive_length(p, ell_min, ell_max, num_real: ti.template()):
    """L(v) = L_min + (L_max - L_min) * normalised entropy of p(c|v)."""
    return ell_min + (ell_max - ell_min) * normalized_entropy(p, num_real)


@ti.func
def fresh_length(m: ti.template(), u, hist: ti.template(), row, t, inv_tau, prior, ell_min, ell_max):
    """Kernel length of map voxel u given this scan's evidence hist[row, :]: the entropy of
    p(c|v) = prior + decayed counters + the scan's histogram (steps 4-5)."""
    alpha = decay_factor(t - m.t_last[u], inv_tau)
    p = ti.Vector([0.0] * m.C)
    for c in ti.static(range(m.C)):
        p[c] = prior + alpha * m.counts[u, c] + hist[row, c]
    return adaptive_length(p, ell_min, ell_max, m.C - 1)
