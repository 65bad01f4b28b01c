"""Step 8: temporal fusion sigma_t = alpha * sigma_{t-1} + delta_t, alpha = exp(-dt / tau).

The decay is lazy: a voxel is decayed only when it is updated, by the time since its own last
update. argmax and normalised probabilities are unchanged by a common scale, so queries never
need to decay.

Also the whole update of csm (counting, no kernel): each training voxel's own histogram.
"""

import numpy as np
import taichi as ti
from taichi.lang.argpack import ArgPack
from tisem.kernels.layout import MapFields
from tisem.kernels.params import EXPONENTIAL, FORGET, PER_CLASS
from tisem.kernels.training import visit_training_voxels


@ti.func
def decay_factor(dt, inv_tau, decay: ti.template()):
    """alpha = exp(-dt / tau) (inv_tau = 0: plain accumulation, alpha = 1); 0 when `decay` is
    FORGET (tau = 0: dt / tau is not a number at dt = 0)."""
    alpha = 0.0
    if ti.static(decay != FORGET):
        alpha = ti.exp(-ti.max(dt, 0.0) * inv_tau)
    return alpha


@ti.func
def class_decay(m: ti.template(), alpha, dt, c: ti.template(), decay: ti.template()):
    """The decay of class c's counter: the common alpha, or with PER_CLASS its own
    exp(-dt / tau_c) (m.class_inv_tau)."""
    a = alpha
    if ti.static(decay == PER_CLASS):
        a = ti.exp(-ti.max(dt, 0.0) * m.class_inv_tau[c])
    return a


@ti.func
def fuse_voxel(m: ti.template(), u, delta, t_rel, inv_tau, decay: ti.template()):
    """Fold one voxel's new evidence into its counters (only the voxel's own thread calls this)."""
    dt = t_rel - m.t_last_rel[u]
    alpha = decay_factor(dt, inv_tau, decay)
    for c in ti.static(range(m.C)):
        m.counts[u, c] = class_decay(m, alpha, dt, c, decay) * m.counts[u, c] + delta[c]
    if ti.static(m.free_space):
        m.occupancy[u] *= alpha  # the occupancy evidence fades with the static tau
    m.t_last_rel[u] = t_rel


@ti.func
def decay_voxel_to(m: ti.template(), u, t_rel, inv_tau, decay: ti.template()):
    """Decay voxel u's counters and occupancy to t_rel without new evidence (a voxel a ray
    crosses): the lazy decay's invariant, everything as of t_last_rel, holds on."""
    if m.t_last_rel[u] < t_rel:
        fuse_voxel(m, u, ti.Vector([0.0] * m.C), t_rel, inv_tau, decay)


@ti.func
def _no_block_work(m: ti.template(), s: ti.template(), i):
    pass


@ti.func
def _fuse_histogram(m: ti.template(), s: ti.template(), u, row, hist: ti.template()):
    h = ti.Vector([0.0] * m.C)
    for c in ti.static(range(m.C)):
        h[c] = hist[row, c]
    # no decay (csm accumulates): alpha = exp(-dt * 0) = 1
    fuse_voxel(m, u, h, s.time_rel_s, 0.0, EXPONENTIAL)


def fuse_histograms(
    m: MapFields, s: ArgPack, blocks: np.ndarray, voxel: np.ndarray, hist: np.ndarray
) -> None:
    """csm's update (steps 6-8 without a kernel): every training voxel adds its own histogram
    (row `hist` of the scan's training rows, kernels/training.py) to its counters."""
    visit_training_voxels(m, s, blocks, voxel, hist, _no_block_work, _fuse_histogram)
