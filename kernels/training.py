"""Step 3 and the training points: filter the scan's voxels and write the training points
(centroid + class evidence) sorted by leaf block. In the adaptive modes each kept voxel's
kernel length is left to the kernel update (kernels/bki.py), which reads its counters anyway;
a voxel only gets its training row here.

Sorting by block lets the kernel update visit only the training points of the few blocks
around a voxel instead of every voxel cell within its kernel length. Three steps: rasterising
counts per block the voxels with at least `min_points` points (kernels/rasterize.py),
`assign_slots` hands out each block's slice of the arrays (the blocks of a table column in z
order, so a column's z-range is one slice), `write_training` fills every slot: the voxels that
carry class evidence, and an unreachable filler for those with only unlabeled points.
"""
import taichi as ti

from kernels.fusion import fuse_voxel
from kernels.layout import LEAF

UNREACHABLE_M = 1.0e15   # a filler training point's coordinates: d^2 ~ 3e30, finite in float32


@ti.func
def block_cell(m: ti.template(), I, center):
    """Table cell of the leaf block holding scan-layer voxel I (always inside: see Mapper)."""
    center_blk = ti.floor(center / LEAF, ti.i32)
    i, _ = m.table_index(m.s_unwrap_blk(I // LEAF, center_blk), center_blk)
    return i


@ti.kernel
def assign_slots(m: ti.template(), stamp: ti.i32, reach_blk: ti.i32) -> ti.i32:
    """Hand each block its slice of the training arrays, and mark in `near` the coarse cells
    of every block within `reach_blk` of it (the map blocks the kernel update visits).

    The blocks of one (x, y) column of the table get consecutive slices in z order, so any
    z-range of a column is one contiguous slice (kernels/bki.py). Every cell of a used column
    gets its start, empty ones too; clear_table resets them.
    """
    m.counter[None] = 0
    for cx, cy in m.col_count:
        n = m.col_count[cx, cy]
        if n > 0:
            slot = ti.atomic_add(m.counter[None], n)
            for cz in range(2 * m.table_half[2] + 1):
                k = m.b_count[cx, cy, cz]
                m.b_start[cx, cy, cz] = slot
                if k > 0:
                    slot += k
                    m.b_count[cx, cy, cz] = 0     # the fill cursor; write_training counts it back up
                    # the table's margin (Mapper) keeps the cell +- reach_blk inside it
                    i = ti.Vector([cx, cy, cz])
                    lo = m.near_index(i - reach_blk)
                    hi = m.near_index(i + reach_blk)
                    for nx in range(lo[0], hi[0] + 1):
                        for ny in range(lo[1], hi[1] + 1):
                            for nz in range(lo[2], hi[2] + 1):
                                m.near[nx, ny, nz] = stamp
    return m.counter[None]


@ti.kernel
def clear_table(m: ti.template()):
    """Reset the training table after a scan: every cell of every used column."""
    for cx, cy in m.col_count:
        if m.col_count[cx, cy] > 0:
            m.col_count[cx, cy] = 0
            for cz in range(2 * m.table_half[2] + 1):
                m.b_count[cx, cy, cz] = 0
                m.b_start[cx, cy, cz] = 0


@ti.func
def reset_scan_voxel(m: ti.template(), I, stamp):
    """Zero a scan-layer voxel once read and clear its bit; its block, stamped as used by this
    scan, stays allocated (rasterize.free_idle_blocks)."""
    for c in ti.static(range(m.C)):
        m.s_hist[I, c] = 0.0
    for a in ti.static(range(3)):
        m.s_sum[I, a] = 0.0
    m.s_npts[I] = 0
    ti.deactivate(m.s_vox, I)
    m.s_stamp[I // LEAF] = stamp


@ti.kernel
def write_training(m: ti.template(), center: ti.types.vector(3, ti.i32), stamp: ti.i32,
                   t: ti.f32, min_points: ti.i32, unit_weight: ti.i32, ell_min: ti.f32,
                   adaptive: ti.i32, counting: ti.i32,
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
        npts = m.s_npts[I]
        centroid = ti.Vector([m.s_sum[I, 0], m.s_sum[I, 1], m.s_sum[I, 2]]) / ti.cast(npts, ti.f32)
        reset_scan_voxel(m, I, stamp)
        if npts >= min_points:
            # rasterize gave every voxel with min_points points a slot; slices are filled end
            # to end (the kernel update reads a column's blocks as one slice)
            cell = block_cell(m, I, center)
            slot = m.b_start[cell] + ti.atomic_add(m.b_count[cell], 1)
            if total <= 0:
                # points but no evidence (only unlabeled ones): a filler no kernel reaches
                for a in ti.static(range(3)):
                    out_xyz[slot, a] = UNREACHABLE_M
                out_classes[slot] = 0
                out_single[slot] = 0
                continue
            written += 1
            u = m.wrap(m.s_unwrap(I, center))       # the same voxel in the map layer
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
            for a in ti.static(range(3)):
                out_xyz[slot, a] = centroid[a]
            if counting:
                # csm: the voxel's own histogram is the whole update, accumulated without decay
                m.ell[u] = ell_min                  # any positive value marks the voxel live
                fuse_voxel(m, u, h, t, 0.0)
            elif adaptive:
                # the length needs the voxel's counters, which the kernel update reads anyway
                # (one pass over the map instead of two): it computes the length from the row
                # (exact in float32 up to 2^24 rows; writing activates the map voxel)
                m.ell[u] = -ti.cast(slot + 1, ti.f32)
            else:
                m.ell[u] = ell_min
    return written
