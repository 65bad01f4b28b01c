"""Steps 6-8: the compact-support sparse kernel, the Bayesian kernel update and its fusion,
with the adaptive length of step 5 computed in the same pass for the voxels the scan hit.

Gather form: each live map voxel v near the scan sums k(v, p) * h(p) over the training points
within its own kernel length L(v) (within `kernel_cutoff` of it: the kernel's last stretch
holds next to nothing, docs/method.md), then folds the sum into its counters. The work per voxel
grows with L(v)^3, so low-entropy voxels (short kernels) are cheap: the adaptive kernel pays
only where the map is uncertain. No atomics: each voxel is written by one thread.

Evidence caps (settings.evidence_caps): the evidence of class c reaches receiver v with the
kernel of length min(L(v), cap_c), a per-class table read and a max per (hit, class); L(v)
itself, and with it every distance test, is unchanged.

Training points are sorted by leaf block, the blocks of each (x, y) column of the table one
after another in z, and a block's rows by voxel, z layer by z layer (kernels/training.py): a
voxel reads, per column its kernel sphere touches, the one slice of rows in the voxel layers
the sphere reaches there, not every voxel cell within reach.
"""

import functools
import math

import numpy as np
import taichi as ti
from tisem.kernels.entropy import fresh_length
from tisem.kernels.fusion import fuse_voxel
from tisem.kernels.layout import (
    LEAF,
    LEAF_BITS,
    is_pending,
    local_of_index,
    pending_row,
    rows_below,
    rows_to,
)
from tisem.kernels.params import KernelSettings, ScanParams

VOXELS = LEAF**3
HITS = 32  # hit list length: hits are summed in batches, after the distance tests

# Evidence below this is float noise at the kernel's edge (g -> 0 as d -> L), not an update:
# counting it would reset the voxel's time and, with alpha = 0, wipe the voxel's history.
MIN_UPDATE = 1e-6


@ti.func
def sparse_kernel(r):
    """Melkumyan-Ramos g(r) for r = d / L in [0, 1): 1 at r = 0, 0 with zero slope at r = 1."""
    two_pi_r = 2.0 * math.pi * r
    g = (2.0 + ti.cos(two_pi_r)) / 3.0 * (1.0 - r) + ti.sin(two_pi_r) / (2.0 * math.pi)
    return ti.max(g, 0.0)  # the two terms cancel near r = 1: never let rounding go negative


@ti.kernel
def fill_kernel_table(m: ti.template()):
    n = m.kernel_lut.shape[0] - 1
    for i in m.kernel_lut:
        m.kernel_lut[i] = sparse_kernel(ti.sqrt(ti.min(i / n, 1.0)))  # entries are spaced in r^2


@ti.func
def sparse_kernel_of_r2(m: ti.template(), r2):
    """g as a function of r^2 = (d / L)^2, linearly interpolated in a table.

    Indexing by r^2 saves the square root, and the table saves a sine and a cosine per
    (voxel, point) pair: the interpolation error is below 1e-6 of sigma0 (tested).
    """
    n = m.kernel_lut.shape[0] - 1
    x = ti.min(r2, 1.0) * n
    i = ti.min(ti.cast(x, ti.i32), n - 1)
    f = x - i
    return (1.0 - f) * m.kernel_lut[i] + f * m.kernel_lut[i + 1]


@ti.func
def axis_gap(x, lo, width):
    """Distance along one axis from coordinate x to the interval [lo, lo + width]."""
    return ti.max(lo - x, 0.0) + ti.max(x - lo - width, 0.0)


@ti.func
def cell_and_layer(z, inv_res, base_z):
    """(table cell, z layer in its block) of local height z: shifts, as Taichi's integer
    floor division costs a sign fix-up, and this runs a million times per scan."""
    v = ti.floor(z * inv_res, ti.i32)
    return (v >> LEAF_BITS) + base_z, v & (LEAF - 1)


@ti.func
def reached_block(m: ti.template(), B, center_blk, stamp):
    """(world index of map leaf block B, whether a training block of the scan with `stamp` can
    reach it). entropy.assign_lengths marked the coarse cells: a superset, the distance tests
    decide."""
    wb = m.unwrap_blk(B, center_blk)
    i, inside = m.table_index(wb, center_blk)
    near = 0
    if inside and m.near[m.near_index(i)] == stamp:
        near = 1
    return wb, near


@ti.func
def voxel_centre(wb, local, resolution):
    """Local metric coordinates of the centre of voxel `local` of world leaf block wb."""
    return ((wb * LEAF + local).cast(ti.f32) + 0.5) * resolution


def evidence_cap_table(caps_m: np.ndarray) -> np.ndarray:
    """The update's per-class table of evidence caps: 1 / cap_c^2 (float32), 0 for no cap
    (an infinite cap_c)."""
    caps = np.asarray(caps_m, np.float64)
    return np.where(np.isfinite(caps), 1.0 / np.square(caps), 0.0).astype(np.float32)


@ti.func
def capped_kernel(m: ti.template(), d2, inv_ell2, cap_inv2):
    """g for evidence at squared distance d2 from a receiver of length L (inv_ell2 = 1 / L^2),
    of a class whose evidence reaches at most cap (cap_inv2 = 1 / cap^2, 0 for no cap): the
    kernel of length min(L, cap), 0 beyond it."""
    r2 = d2 * ti.max(inv_ell2, cap_inv2)
    k = sparse_kernel_of_r2(m, r2)
    if r2 >= 1.0:  # the table's last entry is g(1) in float32, a little above 0
        k = 0.0
    return k


@ti.func
def add_hits(
    m: ti.template(),
    acc: ti.template(),
    hit_p: ti.template(),
    hit_r2: ti.template(),
    n_hits,
    inv_ell2,
    hist: ti.template(),
    classes: ti.template(),
    single: ti.template(),
    cap_inv2: ti.template(),
    capped: ti.template(),
):
    """Add to acc the kernel-weighted evidence of the first n_hits training rows of the hit
    list (local vectors by reference: by value, Taichi copied all three at every call).
    `capped`: each class's evidence takes the kernel of its own cap (`cap_inv2`, per class)."""
    for h in range(n_hits):
        p = hit_p[h]
        k = 0.0
        if ti.static(not capped):
            k = sparse_kernel_of_r2(m, hit_r2[h] * inv_ell2)
        c1 = single[p]
        if c1 > 0:  # one class: the common case
            if ti.static(capped):
                k = capped_kernel(m, hit_r2[h], inv_ell2, cap_inv2[c1])
            acc[c1] += k * hist[p, c1]
        else:
            mask = classes[p]
            for c in ti.static(range(1, m.C)):
                if mask & (1 << c):
                    if ti.static(capped):
                        k = capped_kernel(m, hit_r2[h], inv_ell2, cap_inv2[c])
                    acc[c] += k * hist[p, c]


@functools.cache
def update_kernel(settings: KernelSettings):
    """The kernel update for one kernel-length rule, decay, parallel loop and evidence caps
    (`settings`)."""
    decay = settings.decay
    capped = settings.evidence_caps

    @ti.func
    def update_voxel(
        m: ti.template(),
        u,
        stored,
        centre,
        base,
        blk_m,
        t_rel,
        inv_tau,
        sigma0,
        prior,
        ell_min,
        ell_max,
        cutoff,
        xyz: ti.template(),
        hist: ti.template(),
        classes: ti.template(),
        single: ti.template(),
        cap_inv2: ti.template(),
    ):
        """One live voxel (`stored` = m.length[u]: its kernel length, or a pending mark): its
        length if the scan brought it evidence, the kernel-weighted sum over the training
        points within `cutoff` times that length, and the fusion.

        The scan's constants come by value (copied per voxel, before the loops): where the
        compiler finds them decides how fast math associates the sums, and this keeps the map
        bitwise what it has been."""
        ell = stored  # the kernel length L(v), metres
        if ti.static(settings.adaptive):
            if is_pending(stored):  # evidence in this scan: the length first
                ell = fresh_length(
                    m,
                    u,
                    hist,
                    pending_row(stored),
                    t_rel,
                    inv_tau,
                    prior,
                    ell_min,
                    ell_max,
                    decay,
                    settings.long_kernel_classes,
                    settings.long_kernel_share,
                    settings.long_kernel_min_neighbours,
                )
                m.length[u] = ell
        if ell > 0:
            inv_ell2 = 1.0 / (ell * ell)  # the kernel's argument is d^2 / L^2
            # the points the sum takes lie within reach (cutoff 1: reach is ell, bitwise)
            reach = ell * cutoff
            reach2 = reach * reach
            inv_blk = 1.0 / blk_m
            inv_res = LEAF * inv_blk
            lo = ti.floor((centre - reach) * inv_blk, ti.i32)
            hi = ti.floor((centre + reach) * inv_blk, ti.i32)
            acc = ti.Vector([0.0] * m.C)
            hit_p = ti.Vector([0] * HITS, dt=ti.i32)  # training rows within reach, their d^2
            hit_r2 = ti.Vector([0.0] * HITS)
            n_hits = 0
            # plain nested loops (ti.ndrange would flatten them with an integer division and
            # modulo per iteration) over the table's columns, pruned with the distance from the
            # voxel centre to each column's box in x and y; the voxel layers the sphere reaches
            # there are one slice of training rows (kernels/training.py)
            for bx in range(lo[0], hi[0] + 1):
                gx = axis_gap(centre[0], bx * blk_m, blk_m)
                tx = base[0] + bx
                for by in range(lo[1], hi[1] + 1):
                    gy = axis_gap(centre[1], by * blk_m, blk_m)
                    gxy = gx * gx + gy * gy
                    ty = base[1] + by
                    # inside the table by construction: training blocks lie within the scan's
                    # limit, receivers within NEAR + reach of one, their kernels within reach
                    # more; the table's margin (layout.table_half_blocks) is wider than that.
                    # Checked under ti.init(debug=True) only: taichi compiles an assert into
                    # release kernels too, a call per column (1-3 ms per real scan)
                    if ti.static(ti.lang.impl.current_cfg().debug):
                        assert m.in_table(ti.Vector([tx, ty, 0]))
                    col_lo = m.col_lo[tx, ty]
                    col_hi = m.col_hi[tx, ty]
                    # a column the sphere reaches and that holds points of the scan (most that a
                    # sphere reaches hold none: this test first spares them the rest)
                    if gxy < reach2 and col_lo <= col_hi:
                        dz = ti.sqrt(reach2 - gxy)
                        # the lowest and highest voxel layer the sphere reaches here, clipped to
                        # the cells that hold the scan's points
                        zlo, llo = cell_and_layer(centre[2] - dz, inv_res, base[2])
                        zhi, lhi = cell_and_layer(centre[2] + dz, inv_res, base[2])
                        if zlo < col_lo:
                            zlo = col_lo
                            llo = 0
                        if zhi > col_hi:
                            zhi = col_hi
                            lhi = LEAF - 1
                        if zlo <= zhi:
                            start = m.b_start[tx, ty, zlo] + rows_below(
                                m.b_layers[tx, ty, zlo], llo
                            )
                            end = m.b_start[tx, ty, zhi] + rows_to(m.b_layers[tx, ty, zhi], lhi)
                            for p in range(start, end):
                                # no branch on the distance test, whose outcome no predictor can
                                # guess (~40 % hits): every candidate is written to the hit
                                # list, and only a hit moves its end on
                                d = ti.Vector([xyz[p, 0], xyz[p, 1], xyz[p, 2]]) - centre
                                d2 = d.dot(d)
                                hit_p[n_hits] = p
                                hit_r2[n_hits] = d2
                                n_hits += ti.cast(d2 < reach2, ti.i32)
                                if n_hits == HITS:
                                    add_hits(
                                        m,
                                        acc,
                                        hit_p,
                                        hit_r2,
                                        n_hits,
                                        inv_ell2,
                                        hist,
                                        classes,
                                        single,
                                        cap_inv2,
                                        capped,
                                    )
                                    n_hits = 0
            add_hits(
                m, acc, hit_p, hit_r2, n_hits, inv_ell2, hist, classes, single, cap_inv2, capped
            )
            acc *= sigma0
            if acc.sum() > MIN_UPDATE:
                fuse_voxel(m, u, acc, t_rel, inv_tau, decay)

    @ti.kernel
    def gather_update(
        m: ti.template(),
        s: ScanParams,
        xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (K, 3) training points
        hist: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (K, C) block-sorted
        classes: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (K,) bit c: hist > 0
        single: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (K,) the one class
        cap_inv2: ti.types.ndarray(dtype=ti.f32, ndim=1),
    ):  # (C,) 1 / cap^2
        """The update of every live voxel a training point can reach.

        The parallel loop (settings.per_voxel): on a CPU one task per leaf block (two threads,
        and the block's near test done once), on a GPU one thread per voxel (a thread per block
        would run 64 voxels' gathers one after another on a few thousand threads).
        """
        blk_m = LEAF * s.resolution_m
        center_blk = ti.floor(s.center_vox / LEAF, ti.i32)
        base = ti.Vector(m.table_half) - center_blk
        if ti.static(settings.per_voxel):
            for u in ti.grouped(m.t_last_rel):
                B = u // LEAF
                wb, near = reached_block(m, B, center_blk, s.stamp)
                if near:
                    local = u - B * LEAF
                    update_voxel(
                        m,
                        u,
                        m.length[u],
                        voxel_centre(wb, local, s.resolution_m),
                        base,
                        blk_m,
                        s.time_rel_s,
                        s.inv_tau,
                        s.sigma0,
                        s.prior,
                        s.length_min_m,
                        s.length_max_m,
                        s.kernel_cutoff,
                        xyz,
                        hist,
                        classes,
                        single,
                        cap_inv2,
                    )
        else:
            for B in ti.grouped(m.blk):
                wb, near = reached_block(m, B, center_blk, s.stamp)
                if near:
                    # the block's 64 lengths first, in an unrolled loop: the compiler then walks
                    # the sparse tree to the block once, not once per cell (0 marks a free cell)
                    lengths = ti.Vector([0.0] * VOXELS)
                    for layer in ti.static(range(LEAF)):  # (nested: Taichi warns past 32)
                        for q in ti.static(range(layer * LEAF * LEAF, (layer + 1) * LEAF * LEAF)):
                            lengths[q] = m.length[B * LEAF + local_of_index(q)]
                    for q in range(VOXELS):
                        if lengths[q] != 0:
                            local = local_of_index(q)
                            update_voxel(
                                m,
                                B * LEAF + local,
                                lengths[q],
                                voxel_centre(wb, local, s.resolution_m),
                                base,
                                blk_m,
                                s.time_rel_s,
                                s.inv_tau,
                                s.sigma0,
                                s.prior,
                                s.length_min_m,
                                s.length_max_m,
                                s.kernel_cutoff,
                                xyz,
                                hist,
                                classes,
                                single,
                                cap_inv2,
                            )

    return gather_update
