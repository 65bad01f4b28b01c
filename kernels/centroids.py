"""Sub-voxel class boundaries: where in its voxel each of the voxel's two leading classes lies.

A 0.2 m voxel on a curb holds road and sidewalk points, on a car's edge car and road: its argmax
answers one class for both sides, and the network's own per-point labels beat the map there.
So each voxel keeps two slots, (class, weight, mean position in the voxel), fed by the voxel's
own points (never by the kernel's spread evidence): per scan the training pass finds the two
classes with the most evidence in each voxel and the mean offset of their points from the
voxel's corner (kernels/training.py), and `merge_row` folds them into the map's slots in the
length pass over the same voxels (kernels/entropy.py).
A query point then takes the nearer class's label when the voxel's second class holds at least
`centroid_ratio` of its leading class's evidence and both have a slot (`nearer_class`).

Slots are a two-entry frequent-items summary (Misra-Gries): a class already in a slot adds to
it (weighted mean); a new class takes an empty slot, or replaces the lighter slot when it brings
at least that slot's weight, else wears the lighter slot down by its own. Weights decay like the
counters (exp(-dt / tau) since the voxel's last update, per class with PER_CLASS), so a slot
held by what moved away yields to what is seen there next.

Columns of `m.centroids[u, :]` and of the training rows' `cent[row, :]` (CENTROID_COLS):
slot 0 = (class, weight, x, y, z), slot 1 the same; x, y, z the mean offset from the voxel's
low corner in metres, in [0, resolution); class 0 and weight 0: an empty slot.
"""

import functools

import taichi as ti
from tisem.kernels.fusion import decay_factor
from tisem.kernels.params import PER_CLASS

from tisem.class_centroids import CENTROID_COLS, MIN_SEPARATION, SLOT


@functools.cache
def merge_row(decay: str):
    """The ti.func that folds training row `row`'s class centroids (`cent`) into the slots of
    its map voxel u, for one decay rule (kernels/params.py). kernels/entropy.py calls it from
    the length pass over the scan's training voxels, before the kernel update, while each
    voxel's t_last_rel is still its previous update."""

    @ti.func
    def merge(m: ti.template(), s: ti.template(), u, row, cent: ti.template()):
        # (reads and writes only what changes: most rows bring the class a slot already
        # holds, and every access walks the sparse tree)
        dt = s.time_rel_s - m.t_last_rel[u]
        alpha = decay_factor(dt, s.inv_tau, decay)
        cls = ti.Vector([ti.cast(m.centroids[u, 0], ti.i32), ti.cast(m.centroids[u, SLOT], ti.i32)])
        wgt = ti.Vector([0.0, 0.0])
        for k in ti.static(range(2)):
            a = alpha
            if ti.static(decay == PER_CLASS):
                a = ti.exp(-ti.max(dt, 0.0) * m.class_inv_tau[cls[k]])
            wgt[k] = a * m.centroids[u, k * SLOT + 1]
        # (a FORGET map keeps this scan's slots only: every weight decayed to 0 above)
        for r in ti.static(range(2)):
            w = cent[row, r * SLOT + 1]
            if w > 0:
                c = ti.cast(cent[row, r * SLOT], ti.i32)
                k = -1
                if cls[0] == c:
                    k = 0
                elif cls[1] == c:
                    k = 1
                if k >= 0:  # the class holds a slot: its mean moves, weighted
                    total = wgt[k] + w
                    for d in ti.static(range(3)):
                        at = k * SLOT + 2 + d
                        m.centroids[u, at] = (
                            m.centroids[u, at] * wgt[k] + cent[row, r * SLOT + 2 + d] * w
                        ) / total
                    wgt[k] = total
                else:
                    j = 0 if wgt[0] <= wgt[1] else 1  # the empty or lighter slot
                    if w >= wgt[j]:  # taken over
                        cls[j] = c
                        wgt[j] = w
                        for d in ti.static(range(3)):
                            m.centroids[u, j * SLOT + 2 + d] = cent[row, r * SLOT + 2 + d]
                    else:  # worn down
                        wgt[j] -= w
        for k in ti.static(range(2)):
            if wgt[k] <= 0:  # worn down to nothing: an empty slot
                cls[k] = 0
                wgt[k] = 0.0
            m.centroids[u, k * SLOT] = ti.cast(cls[k], ti.f32)
            m.centroids[u, k * SLOT + 1] = wgt[k]

    return merge


@ti.func
def nearer_class(m: ti.template(), u, offset, best, second, res):
    """`best`, or `second` when both classes hold a slot of voxel u, their centroids lie more
    than MIN_SEPARATION voxels apart, and the point at `offset` from the voxel's low corner
    lies nearer the second's centroid."""
    label = best
    c0 = ti.cast(m.centroids[u, 0], ti.i32)
    c1 = ti.cast(m.centroids[u, SLOT], ti.i32)
    kb = -1
    ks = -1
    if c0 == best and c1 == second:
        kb = 0
        ks = 1
    elif c1 == best and c0 == second:
        kb = 1
        ks = 0
    if kb >= 0 and m.centroids[u, kb * SLOT + 1] > 0 and m.centroids[u, ks * SLOT + 1] > 0:
        db = 0.0
        ds = 0.0
        sep = 0.0
        for d in ti.static(range(3)):
            eb = offset[d] - m.centroids[u, kb * SLOT + 2 + d]
            es = offset[d] - m.centroids[u, ks * SLOT + 2 + d]
            gap = m.centroids[u, kb * SLOT + 2 + d] - m.centroids[u, ks * SLOT + 2 + d]
            db += eb * eb
            ds += es * es
            sep += gap * gap
        if ds < db and sep > (MIN_SEPARATION * res) ** 2:
            label = second
    return label


@ti.kernel
def gather_centroids(
    m: ti.template(),
    keys: ti.types.ndarray(dtype=ti.i32, ndim=2),  # (M, 3) live voxels
    out: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (M, CENTROID_COLS) out
):
    """The class centroid slots of the given live voxels."""
    for i in range(keys.shape[0]):
        u = m.wrap(ti.Vector([keys[i, 0], keys[i, 1], keys[i, 2]]))
        for k in ti.static(range(CENTROID_COLS)):
            out[i, k] = m.centroids[u, k]


@ti.kernel
def scatter_centroids(
    m: ti.template(),
    keys: ti.types.ndarray(dtype=ti.i32, ndim=2),  # (M, 3) live voxels
    cent: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (M, CENTROID_COLS)
):
    """Write the class centroid slots of voxels just imported into the window."""
    for i in range(keys.shape[0]):
        u = m.wrap(ti.Vector([keys[i, 0], keys[i, 1], keys[i, 2]]))
        for k in ti.static(range(CENTROID_COLS)):
            m.centroids[u, k] = cent[i, k]
