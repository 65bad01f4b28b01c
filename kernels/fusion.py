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


@ti.func
def fuse_voxel(m: ti.template(), u, delta, t, inv_tau):
    """Fold one voxel's new evidence into its counters (only the voxel's own thread calls this)."""
    alpha = decay_factor(t - m.t_last[u], inv_tau)
    for c in ti.static(range(m.C)):
        m.counts[u, c] = alpha * m.counts[u, c] + delta[c]
    m.t_last[u] = t
