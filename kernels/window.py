"""The live window: find leaf blocks outside it, export their voxels, free them.

Block indices here are storage leaf-block indices (voxel // LEAF), as struct-fors over the
block SNode yield them; they are unwrapped around the window centre (in blocks) like voxels.
"""
import taichi as ti

from kernels.layout import LEAF, MID


@ti.func
def unwrap_cells(u, center, n: ti.template()):
    w = ti.Vector([0, 0, 0])
    for a in ti.static(range(3)):
        d = (u[a] - center[a]) & (n[a] - 1)
        if d >= n[a] // 2:
            d -= n[a]
        w[a] = center[a] + d
    return w


@ti.kernel
def find_far_blocks(m: ti.template(),
                    old_center_blk: ti.types.vector(3, ti.i32),
                    new_center_blk: ti.types.vector(3, ti.i32),
                    half_blk: ti.types.vector(3, ti.i32),
                    out_blocks: ti.types.ndarray(dtype=ti.i32, ndim=2)) -> ti.i32:   # (K, 3)
    m.counter[None] = 0
    for B in ti.grouped(m.blk):
        wb = unwrap_cells(B, old_center_blk, m.N_blk)
        off = ti.abs(wb - new_center_blk)
        if off[0] > half_blk[0] or off[1] > half_blk[1] or off[2] > half_blk[2]:
            idx = ti.atomic_add(m.counter[None], 1)
            if idx < out_blocks.shape[0]:
                for a in ti.static(range(3)):
                    out_blocks[idx, a] = B[a]
    return m.counter[None]


@ti.kernel
def export_blocks(m: ti.template(), center: ti.types.vector(3, ti.i32),
                  blocks: ti.types.ndarray(dtype=ti.i32, ndim=2), n_blocks: ti.i32,
                  keys: ti.types.ndarray(dtype=ti.i32, ndim=2),
                  counts: ti.types.ndarray(dtype=ti.f32, ndim=2),
                  t_last: ti.types.ndarray(dtype=ti.f32, ndim=1),
                  ell: ti.types.ndarray(dtype=ti.f32, ndim=1)) -> ti.i32:
    """Export the live voxels of the listed storage blocks (world keys unwrapped at `center`)."""
    m.counter[None] = 0
    for b, i, j, k in ti.ndrange(n_blocks, LEAF, LEAF, LEAF):
        u = ti.Vector([blocks[b, 0] * LEAF + i, blocks[b, 1] * LEAF + j, blocks[b, 2] * LEAF + k])
        if ti.is_active(m.vox, u):
            idx = ti.atomic_add(m.counter[None], 1)
            if idx < keys.shape[0]:
                w = m.unwrap(u, center)
                for a in ti.static(range(3)):
                    keys[idx, a] = w[a]
                for c in ti.static(range(m.C)):
                    counts[idx, c] = m.counts[u, c]
                t_last[idx] = m.t_last[u]
                ell[idx] = m.ell[u]
    return m.counter[None]


@ti.kernel
def free_blocks(m: ti.template(), blocks: ti.types.ndarray(dtype=ti.i32, ndim=2), n_blocks: ti.i32):
    for b in range(n_blocks):
        ti.deactivate(m.blk, [blocks[b, 0], blocks[b, 1], blocks[b, 2]])


@ti.kernel
def free_far_top_cells(m: ti.template(), old_center_top: ti.types.vector(3, ti.i32),
                       new_center_blk: ti.types.vector(3, ti.i32),
                       half_blk: ti.types.vector(3, ti.i32)):
    """Free top cells all of whose blocks lie outside the window (they were freed just before)."""
    for T in ti.grouped(m.top):
        wt = unwrap_cells(T, old_center_top, m.N_top)
        far = 0
        for a in ti.static(range(3)):
            lo = wt[a] * MID
            hi = lo + MID - 1
            if lo > new_center_blk[a] + half_blk[a] or hi < new_center_blk[a] - half_blk[a]:
                far = 1
        if far:
            ti.deactivate(m.top, T)
