"""Step 8: temporal fusion sigma_t = alpha * sigma_{t-1} + delta_t, alpha = exp(-dt / tau).

The decay is lazy: a voxel is decayed only when it is updated, by the time since its own last
update. argmax and normalised probabilities are unchanged by a common scale, so queries never
need to decay.
"""
import taichi as ti


@ti.func
def decay_factor(dt, inv_tau):
    """exp(-dt/tau); inv_tau = 0 is plain accumulation, inv_tau < 0 forgets everything (tau = 0)."""
    alpha = 0.0
    if inv_tau >= 0:
        alpha = ti.exp(-ti.max(dt, 0.0) * inv_tau)
    return alpha


@ti.kernel
def fuse(m: ti.template(), t: ti.f32, inv_tau: ti.f32):
    for I in ti.grouped(m.s_npts):
        if m.ell[I] > 0:                      # a live map voxel (reading never activates)
            total = 0.0
            for c in ti.static(range(m.C)):
                total += m.s_delta[I, c]
            if total > 0:
                alpha = decay_factor(t - m.t_last[I], inv_tau)
                for c in ti.static(range(m.C)):
                    m.counts[I, c] = alpha * m.counts[I, c] + m.s_delta[I, c]
                m.t_last[I] = t
