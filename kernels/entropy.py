"""Steps 3-5: redundant-voxel filtering, semantic entropy and the adaptive kernel length.

One pass over the scan layer: every voxel that survives the filter becomes a training point
(its centroid and class histogram, compacted into arrays) and gets its kernel length from the
entropy of p(c|v) = normalize(prior + decayed map counter + h(v)).
"""
import taichi as ti

from kernels.fusion import decay_factor


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
        if q > 0:
            h -= q * ti.log(q)
    return h / ti.log(ti.cast(num_real, ti.f32))


@ti.kernel
def select_training(m: ti.template(),
                    center: ti.types.vector(3, ti.i32),     # window centre (world voxel)
                    t: ti.f32, inv_tau: ti.f32,             # scan time; 1/tau (<0: alpha = 0)
                    min_points: ti.i32, unit_weight: ti.i32, prior: ti.f32,
                    ell_min: ti.f32, ell_max: ti.f32, adaptive: ti.i32, counting: ti.i32,
                    out_xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),    # (K, 3) centroid, local m
                    out_hist: ti.types.ndarray(dtype=ti.f32, ndim=2)    # (K, C) class evidence
                    ) -> ti.i32:
    m.counter[None] = 0
    for I in ti.grouped(m.s_npts):
        n = m.s_npts[I]
        total = 0.0
        for c in ti.static(range(m.C)):
            total += m.s_hist[I, c]
        # filter: too few points, or no class evidence at all (only unlabeled points)
        if n >= min_points and total > 0:
            scale = 1.0
            if unit_weight:
                scale = 1.0 / total
            idx = ti.atomic_add(m.counter[None], 1)
            if idx < out_xyz.shape[0]:
                for a in ti.static(range(3)):
                    out_xyz[idx, a] = m.s_sum[I, a] / n
                for c in ti.static(range(m.C)):
                    out_hist[idx, c] = m.s_hist[I, c] * scale
            if counting:
                # csm: the voxel's own histogram is the whole update
                for c in ti.static(range(m.C)):
                    m.s_delta[I, c] = m.s_hist[I, c] * scale
                m.ell[I] = ell_min            # any positive value marks the voxel live
            else:
                length = ell_min
                if adaptive:
                    alpha = decay_factor(t - m.t_last[I], inv_tau)
                    p = ti.Vector([0.0] * m.C)
                    for c in ti.static(range(m.C)):
                        p[c] = prior + alpha * m.counts[I, c] + m.s_hist[I, c] * scale
                    length = ell_min + (ell_max - ell_min) * normalized_entropy(p, m.C - 1)
                m.ell[I] = length             # writing activates the map voxel
    return m.counter[None]
