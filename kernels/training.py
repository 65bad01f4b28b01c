"""Step 3 and the training points: filter the scan's voxels, give each kept voxel its kernel
length, and write the training points (centroid + class evidence) sorted by leaf block.

Sorting by block lets the kernel update visit only the training points of the few blocks
around a voxel instead of every voxel cell within its kernel length. Three steps: rasterising
counts per block the voxels with at least `min_points` points (kernels/rasterize.py),
`assign_slots` hands out each block's slice of the arrays, `write_training` fills the slices
with the voxels that also carry class evidence. A voxel with points but no evidence (only
unlabeled points) leaves its slot unused at the end of its block's slice: the fill cursor,
not the slice length, is what the kernel update reads.
"""
import taichi as ti

from kernels.entropy import adaptive_length
from kernels.fusion import decay_factor, fuse_voxel
from kernels.layout import LEAF


@ti.func
def block_cell(m: ti.template(), I, center):
    """Table cell of the leaf block holding scan-layer voxel I (always inside: see Mapper)."""
    center_blk = ti.floor(center / LEAF, ti.i32)
    i, _ = m.table_index(m.s_unwrap_blk(I // LEAF, center_blk), center_blk)
    return i


@ti.kernel
def assign_slots(m: ti.template(), center_blk: ti.types.vector(3, ti.i32), stamp: ti.i32,
                 reach_blk: ti.i32) -> ti.i32:
    """Hand each block its slice of the training arrays, and mark in `near` the coarse cells
    of every block within `reach_blk` of it (the map blocks the kernel update visits)."""
    m.counter[None] = 0
    for B in ti.grouped(m.s_blk):
        i, _ = m.table_index(m.s_unwrap_blk(B, center_blk), center_blk)
        n = m.b_count[i]
        if n > 0:
            m.b_start[i] = ti.atomic_add(m.counter[None], n)
            m.b_count[i] = 0     # reused as the fill cursor; write_training counts it back up
            # the table's margin (Mapper) keeps i +- reach_blk inside it
            lo = m.near_index(i - reach_blk)
            hi = m.near_index(i + reach_blk)
            for cx in range(lo[0], hi[0] + 1):
                for cy in range(lo[1], hi[1] + 1):
                    for cz in range(lo[2], hi[2] + 1):
                        m.near[cx, cy, cz] = stamp
    return m.counter[None]


@ti.kernel
def write_training(m: ti.template(), center: ti.types.vector(3, ti.i32),
                   t: ti.f32, inv_tau: ti.f32, min_points: ti.i32, unit_weight: ti.i32,
                   prior: ti.f32, ell_min: ti.f32, ell_max: ti.f32, adaptive: ti.i32,
                   counting: ti.i32,
                   out_xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),    # (K, 3) centroid, local m
                   out_hist: ti.types.ndarray(dtype=ti.f32, ndim=2),   # (K, C) class evidence
                   out_classes: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (K,) bit c: evidence
                   out_single: ti.types.ndarray(dtype=ti.i32, ndim=1)  # (K,) the one class or 0
                   ) -> ti.i32:
    """Fill the training arrays; returns how many training points were written."""
    written = 0
    for I in ti.grouped(m.s_npts):
        h = ti.Vector([0.0] * m.C)
        for c in ti.static(range(m.C)):
            h[c] = m.s_hist[I, c]
        total = h.sum()
        if m.s_npts[I] >= min_points and total > 0:
            written += 1
            cell = block_cell(m, I, center)
            u = m.wrap(m.s_unwrap(I, center))       # the same voxel in the map layer
            slot = m.b_start[cell] + ti.atomic_add(m.b_count[cell], 1)
            if unit_weight:
                h *= 1.0 / total
            mask = 0
            n_classes = 0
            last = 0
            for c in ti.static(range(m.C)):
                out_hist[slot, c] = h[c]
                if h[c] > 0:
                    mask |= 1 << c
                    n_classes += 1
                    last = c
            out_classes[slot] = mask
            # most voxels hold one class: the kernel update then needs one add, not a class loop
            out_single[slot] = last if n_classes == 1 else 0
            n = ti.cast(m.s_npts[I], ti.f32)
            for a in ti.static(range(3)):
                out_xyz[slot, a] = m.s_sum[I, a] / n
            if counting:
                # csm: the voxel's own histogram is the whole update, accumulated without decay
                m.ell[u] = ell_min                  # any positive value marks the voxel live
                fuse_voxel(m, u, h, t, 0.0)
            else:
                length = ell_min
                if adaptive:
                    alpha = decay_factor(t - m.t_last[u], inv_tau)
                    p = ti.Vector([0.0] * m.C)
                    for c in ti.static(range(m.C)):
                        p[c] = prior + alpha * m.counts[u, c] + h[c]
                    length = adaptive_length(p, ell_min, ell_max, m.C - 1)
                m.ell[u] = length                   # writing activates the map voxel
    return written
