"""Steps 4-5: semantic entropy and the kernel length of every voxel the scan hit.

`assign_lengths` gives each training voxel of the scan its kernel length: the fixed one, or, in
the adaptive modes, a pending mark (kernels/layout.py). The adaptive length needs the voxel's
decayed counters, which the kernel update reads anyway, so the update computes it there
(`fresh_length`, called from kernels/bki.py) in the same pass over the map.
"""

import functools
import math

import numpy as np
import taichi as ti
from taichi.lang.argpack import ArgPack
from tisem.kernels import centroids
from tisem.kernels.fusion import decay_factor
from tisem.kernels.layout import MapFields, pending_length
from tisem.kernels.params import ADAPTIVE_LENGTH, NO_KERNEL
from tisem.kernels.training import visit_training_voxels

LN2 = math.log(2.0)


@ti.func
def fast_log(x):
    """Natural log of a positive, normal float32 to ~1e-7 absolute error, without libm.

    The entropy takes 19 logs per voxel of every scan; libm's log was a large share of that
    step, while the kernel length needs nowhere near float precision. x = m * 2^e with m in
    [1, 2); ln m = 2 atanh((m - 1) / (m + 1)) as an odd series in t = (m - 1) / (m + 1) <= 1/3.
    """
    bits = ti.bit_cast(x, ti.i32)
    e = ((bits >> 23) & 0xFF) - 127
    m = ti.bit_cast((bits & 0x007FFFFF) | 0x3F800000, ti.f32)
    t = (m - 1.0) / (m + 1.0)
    t2 = t * t
    ln_m = (
        2.0
        * t
        * (
            1.0
            + t2
            * (
                1.0 / 3.0
                + t2 * (1.0 / 5.0 + t2 * (1.0 / 7.0 + t2 * (1.0 / 9.0 + t2 * (1.0 / 11.0))))
            )
        )
    )
    return ln_m + ti.cast(e, ti.f32) * LN2


@ti.func
def normalized_entropy(p, num_real: ti.template()):
    """Shannon entropy of the unnormalised vector p over classes 1..C-1, divided by log(C-1).

    Class 0 (unlabeled) never receives evidence, so it is left out of the support: a voxel
    with uniform evidence over the 19 real classes gets exactly 1.
    """
    return entropy_with_common(p, num_real, -1.0, 0.0)


@ti.func
def entropy_with_common(p, num_real: ti.template(), common, common_plogp):
    """normalized_entropy, where a class whose p_c equals `common` (the prior, for a class the
    voxel has no evidence for: most classes of most voxels) adds the precomputed
    `common_plogp` = common * ln(common) instead of taking a log.

    As H = ln T - (sum_c p_c ln p_c) / T with T = sum_c p_c: one division per voxel, not one
    per class.
    """
    total = 0.0
    plogp = 0.0
    for c in ti.static(range(1, num_real + 1)):
        total += p[c]
        if p[c] == common:
            plogp += common_plogp
        elif p[c] > 0:
            plogp += p[c] * fast_log(p[c])
    h = 0.0
    if total > 0:
        h = fast_log(total) - plogp / total
    # (rounding can take the difference a hair past [0, ln(C-1)])
    return ti.min(ti.max(h / ti.log(ti.cast(num_real, ti.f32)), 0.0), 1.0)


@ti.func
def length_of(h_norm, ell_min, ell_max):
    """L(v) = L_min + (L_max - L_min) * H(v), H the normalised entropy of p(c|v)."""
    return ell_min + (ell_max - ell_min) * h_norm


@ti.func
def adaptive_length(p, ell_min, ell_max, num_real: ti.template()):
    """The kernel length of unnormalised p(c|v)."""
    return length_of(normalized_entropy(p, num_real), ell_min, ell_max)


@ti.func
def fresh_length(
    m: ti.template(),
    u,
    hist: ti.template(),
    row,
    t_rel,
    inv_tau,
    prior,
    ell_min,
    ell_max,
    decay: ti.template(),
    long_classes: ti.template(),
    long_share: ti.template(),
    min_neighbours: ti.template(),
):
    """Kernel length of map voxel u given this scan's evidence hist[row, :]: the entropy of
    p(c|v) = prior + decayed counters + the scan's histogram (steps 4-5); ell_max where the
    voxel holds one of `long_classes` with at least `long_share` of its leading class's
    evidence (`holds_outvoted_class`) and, with `min_neighbours` > 0, its z layer holds at
    least that many live voxels within 2 of it (`layer_neighbours`)."""
    alpha = decay_factor(t_rel - m.t_last_rel[u], inv_tau, decay)
    p = ti.Vector([0.0] * m.C)
    for c in ti.static(range(m.C)):
        p[c] = prior + alpha * m.counts[u, c] + hist[row, c]
    prior_plogp = 0.0
    if prior > 0:
        prior_plogp = prior * fast_log(prior)
    ell = length_of(entropy_with_common(p, m.C - 1, prior, prior_plogp), ell_min, ell_max)
    if ti.static(len(long_classes) > 0):
        if holds_outvoted_class(p, prior, m.C, long_classes, long_share):
            if ti.static(min_neighbours > 0):
                if layer_neighbours(m, u) >= min_neighbours:
                    ell = ell_max
            else:
                ell = ell_max
    return ell


@ti.func
def layer_neighbours(m: ti.template(), u):
    """How many of the 24 voxels within 2 of storage voxel u in its z layer are live: a patch
    of a fence or a wall is wide in its layer, a pole is not. Liveness, not the neighbours'
    classes: the update fuses their counters in the same pass, on other threads, while the
    voxels live in it were all made live before it (the length pass)."""
    n = 0
    for dx in ti.static(range(-2, 3)):
        for dy in ti.static(range(-2, 3)):
            if ti.static(dx != 0 or dy != 0):
                if ti.is_active(m.vox, m.wrap(u + ti.Vector([dx, dy, 0]))):
                    n += 1
    return n


@ti.func
def holds_outvoted_class(
    p, prior, num_classes: ti.template(), classes: ti.template(), share: ti.template()
):
    """Whether p(c|v) - prior, the voxel's evidence, has one of `classes` at `share` or more
    of the leading class's. Such a voxel takes the longest kernel, so that the evidence around
    it decides: a patch of fence the network calls pole is outvoted by the fence around it,
    while the evidence caps keep that pole evidence from reaching far (docs/method.md)."""
    top = 0.0
    for c in ti.static(range(1, num_classes)):
        top = ti.max(top, p[c] - prior)
    held = False
    for c in ti.static(classes):
        evidence = p[c] - prior
        if evidence > 0 and evidence >= share * top:
            held = True
    return held


@functools.cache
def _length_visitors(kernel_length: str, centroid_decay: str | None):
    """The per-block and per-row work of `assign_lengths` for one kernel-length rule, and with
    `centroid_decay` (a decay rule) the class centroids' merge of the same rows."""
    merges = centroid_decay is not None
    merge = centroids.merge_row(centroid_decay) if merges else None

    @ti.func
    def mark_reach(m: ti.template(), s: ti.template(), i):
        if ti.static(kernel_length != NO_KERNEL):
            mark_near(m, i, s.stamp, s.reach_blk)

    @ti.func
    def assign(m: ti.template(), s: ti.template(), u, row, cent: ti.template()):
        if ti.static(merges):  # (before anything below touches the voxel)
            merge(m, s, u, row, cent)
        if ti.static(kernel_length == ADAPTIVE_LENGTH):
            m.length[u] = pending_length(row)
        else:
            m.length[u] = s.fixed_length_m  # (csm: any positive length marks it live)
        # u is live from now on: `length` is not on the bitmasked node, so a store to a field
        # that is sets the voxel's bit (its time keeps its value; a free cell holds 0). Not
        # ti.activate: in taichi 1.7.4 it leaves the bit clear when it has to allocate the block
        # first (caught by tests/test_kernels.py), and it warns about int32 indices at every
        # compile
        m.t_last_rel[u] = m.t_last_rel[u]

    return mark_reach, assign


@ti.func
def mark_near(m: ti.template(), i, stamp, reach_blk):
    """Mark the coarse `near` cells of every block within reach_blk of table cell i (the map
    blocks the kernel update visits); the table's margin (layout.table_half_blocks) keeps them
    inside it."""
    lo = m.near_index(i - reach_blk)
    hi = m.near_index(i + reach_blk)
    for nx in range(lo[0], hi[0] + 1):
        for ny in range(lo[1], hi[1] + 1):
            for nz in range(lo[2], hi[2] + 1):
                m.near[nx, ny, nz] = stamp


def assign_lengths(
    m: MapFields,
    s: ArgPack,
    blocks: np.ndarray,
    voxel: np.ndarray,
    cent: np.ndarray,
    kernel_length: str,
    decay: str,
) -> None:
    """Steps 4-5 for every voxel the scan's training rows fall in: its kernel length under
    `kernel_length` (kernels/params.py), and the map blocks within kernel reach of it marked for
    the update; in a map with class centroids, in the same pass over the rows, each row's
    class centroids (`cent`, rows of the training pass) folded into its voxel's slots with the
    map's `decay` rule. `voxel`: the training rows' voxel indices."""
    visitors = _length_visitors(kernel_length, decay if m.class_centroids else None)
    visit_training_voxels(m, s, blocks, voxel, cent, *visitors)
