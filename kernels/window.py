"""The live window: find the voxels that leave it, export them, free what they leave
empty.

The window is a box of voxels, |w - center| <= half per axis, the same box the query kernel
reads the field in; everything outside it is in the host store. Leaf blocks that straddle its
face are split: their outside voxels leave (exported, zeroed, their bits cleared), the rest stay,
and a block is freed once it has no voxel left. So a voxel is live exactly when the box holds it,
and a query never looks in the wrong place.

Block indices here are storage leaf-block indices (voxel // LEAF), as struct-fors over the
block SNode yield them; they are unwrapped around a centre (in blocks) like voxels.
"""

import taichi as ti
from tisem.kernels.layout import CENTROID_COLS, LEAF, TOP, deactivate, rows_to
from tisem.kernels.params import ScanParams
from tisem.kernels.query import copy_voxel_out


@ti.func
def outside(lo, hi, center, half):
    """Whether the voxel range [lo, hi] (per axis) pokes out of the box around center."""
    out = 0
    for a in ti.static(range(3)):
        if lo[a] < center[a] - half[a] or hi[a] > center[a] + half[a]:
            out = 1
    return out


@ti.kernel
def find_leaving_blocks(
    m: ti.template(),
    old_center_blk: ti.types.vector(3, ti.i32),  # unwraps storage blocks
    center: ti.types.vector(3, ti.i32),  # the new box, voxels
    half: ti.types.vector(3, ti.i32),
    out_blocks: ti.types.ndarray(dtype=ti.i32, ndim=2),
) -> ti.types.vector(2, ti.i32):  # (K, 3)
    """Live leaf blocks not wholly inside the box (storage indices); returns how many, and how
    many blocks are live (the window needs both when it moves: one pass over the blocks)."""
    m.counter[None] = 0
    live = 0
    for B in ti.grouped(m.blk):
        live += 1
        lo = m.unwrap_blk(B, old_center_blk) * LEAF
        if outside(lo, lo + LEAF - 1, center, half):
            idx = ti.atomic_add(m.counter[None], 1)
            if idx < out_blocks.shape[0]:
                for a in ti.static(range(3)):
                    out_blocks[idx, a] = B[a]
    return ti.Vector([m.counter[None], live])


@ti.kernel
def export_leaving(
    m: ti.template(),
    old_center: ti.types.vector(3, ti.i32),
    center: ti.types.vector(3, ti.i32),
    half: ti.types.vector(3, ti.i32),
    blocks: ti.types.ndarray(dtype=ti.i32, ndim=2),
    n_blocks: ti.i32,
    keys: ti.types.ndarray(dtype=ti.i32, ndim=2),  # (M, 3) out: world voxel
    counts: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (M, C) out
    t_last_rel: ti.types.ndarray(dtype=ti.f32, ndim=1),  # (M,) out
    length_m: ti.types.ndarray(dtype=ti.f32, ndim=1),  # (M,) out
    occupancy: ti.types.ndarray(dtype=ti.f32, ndim=1),  # (M,) out (free space)
    centroids: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (M, CENTROID_COLS) out (centroids)
    left: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (n_blocks,) out
) -> ti.i32:
    """Move the live voxels of the listed blocks that lie outside the box out of the field.

    Each leaving voxel is written to the outputs (world keys unwrapped at `old_center`; its
    occupancy evidence only in a map with free space, its class centroids only in a map that
    keeps them, else `occupancy` and `centroids` may be empty), then zeroed (with compact
    counters, its counters freed) and its bit cleared (a bitmasked cell keeps its data when
    deactivated, and the next voxel there must start from zero). `left[b]` counts block b's
    voxels that stay.
    """
    m.counter[None] = 0
    for b, i, j, k in ti.ndrange(n_blocks, LEAF, LEAF, LEAF):
        u = ti.Vector([blocks[b, 0] * LEAF + i, blocks[b, 1] * LEAF + j, blocks[b, 2] * LEAF + k])
        if ti.is_active(m.vox, u):
            w = m.unwrap(u, old_center)
            if outside(w, w, center, half):
                idx = ti.atomic_add(m.counter[None], 1)
                if idx < keys.shape[0]:
                    copy_voxel_out(m, u, w, idx, keys, counts, t_last_rel, length_m)
                if ti.static(m.free_space):
                    if idx < keys.shape[0]:
                        occupancy[idx] = m.occupancy[u]
                    m.occupancy[u] = 0.0
                    m.free_stamp[u] = 0
                    if ti.static(m.thin_static_hold):
                        m.hit_time[u] = 0.0
                        m.first_hit[u] = 0.0
                    if ti.static(m.thin_static_crossings):
                        m.crossings_since_hit[u] = 0
                if ti.static(m.class_centroids):
                    for k in ti.static(range(CENTROID_COLS)):
                        if idx < keys.shape[0]:
                            centroids[idx, k] = m.centroids[u, k]
                        m.centroids[u, k] = 0.0
                if ti.static(m.compact_counters):
                    # its counters' memory goes back to taichi's pool, which zero-fills it
                    deactivate(m.vox_counts, u)
                else:
                    for c in ti.static(range(m.C)):
                        m.counts[u, c] = 0.0
                m.t_last_rel[u] = 0.0
                m.length[u] = 0.0
                deactivate(m.vox, u)
            else:
                ti.atomic_add(left[b], 1)
    return m.counter[None]


@ti.kernel
def free_empty_blocks(
    m: ti.template(),
    blocks: ti.types.ndarray(dtype=ti.i32, ndim=2),
    n_blocks: ti.i32,
    left: ti.types.ndarray(dtype=ti.i32, ndim=1),
) -> ti.i32:
    """Free the listed blocks that have no voxel left (their memory is recycled zero-filled)."""
    n = 0
    for b in range(n_blocks):
        if left[b] == 0:
            deactivate(m.blk, ti.Vector([blocks[b, 0], blocks[b, 1], blocks[b, 2]]))
            n += 1
    return n


@ti.kernel
def free_far_top_cells(
    m: ti.template(),
    old_center_top: ti.types.vector(3, ti.i32),
    center: ti.types.vector(3, ti.i32),
    half: ti.types.vector(3, ti.i32),
):
    """Free top cells that lie wholly outside the box (their blocks were freed just before)."""
    for T in ti.grouped(m.top):
        lo = m.unwrap_cells(T, old_center_top, m.N_top) * TOP
        hi = lo + TOP - 1
        far = 0
        for a in ti.static(range(3)):
            if lo[a] > center[a] + half[a] or hi[a] < center[a] - half[a]:
                far = 1
        if far:
            deactivate(m.top, T)


@ti.kernel
def blocks_by_ring(
    m: ti.template(),
    old_center_blk: ti.types.vector(3, ti.i32),
    center_blk: ti.types.vector(3, ti.i32),
    half_blk: ti.types.vector(3, ti.i32),
    rings: ti.types.ndarray(dtype=ti.i32, ndim=1),
):  # (half_blk.x + 1,)
    """Live blocks within the block box around center_blk, by Chebyshev x/y distance."""
    for B in ti.grouped(m.blk):
        off = ti.abs(m.unwrap_blk(B, old_center_blk) - center_blk)
        r = ti.max(off[0], off[1])
        if r <= half_blk[0] and off[2] <= half_blk[2]:
            ti.atomic_add(rings[r], 1)


@ti.kernel
def flag_new_blocks(
    m: ti.template(),
    s: ScanParams,
    blocks: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (B,) occupied cells
    new: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (B,) out: 1 = new block
) -> ti.i32:
    """Which occupied cells of the scan's table would make a map leaf block live: 1 for a cell
    with training rows (training.sort_blocks counted them) whose map block is not live yet,
    else 0. Returns how many; reads the tree, activates nothing."""
    base = ti.floor(s.center_vox / LEAF, ti.i32) - ti.Vector(m.table_half)  # cell 0's block
    n = 0
    for b in range(blocks.shape[0]):
        i = m.cell_of_id(blocks[b])
        flag = 0
        if rows_to(m.b_layers[i], LEAF - 1) > 0:
            if not ti.is_active(m.blk, m.wrap_blk(base + i)):
                flag = 1
        new[b] = flag
        n += flag
    return n
