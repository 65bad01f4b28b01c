"""Steps 2-3 and the training points: reduce each leaf block's points (sorted by block in
kernels/rasterize.py) to its voxels, filter them, and write the training points (centroid +
class evidence) sorted by block. In the adaptive modes each kept voxel's kernel length is left
to the kernel update (kernels/bki.py), which reads its counters anyway; a voxel only gets its
training row here.

Three passes, none with float atomics: `sort_blocks`, one task per occupied leaf block, sorts
the block's points by voxel (a counting sort over its 64 voxels) and counts the voxels that pass
the filter (>= min_points points, some class evidence) per z layer; `table.column_slots`, one task
per (x, y) column of the scan's table, hands out the rows, a column's blocks one after another
in z, so that any z-range of a column is one contiguous slice (kernels/bki.py); `write_training`,
one task per block again, sums each voxel's run of points into its row. Tasks per block rather
than per column keep thousands of them busy on a GPU.
"""
import taichi as ti

from kernels.fusion import fuse_voxel
from kernels.layout import LAYER_BITS, LEAF, local_of_index, rows_to
from kernels.rasterize import EVIDENCE, to_local

VOXELS = LEAF ** 3


@ti.func
def sort_block(m: ti.template(), i, min_points, code: ti.template(), perm: ti.template(),
               perm2: ti.template()):
    """Counting-sort block i's points by voxel (perm -> perm2, same slice); returns, packed as
    in b_layers, how many of its voxels pass the filter in each z layer and those below."""
    s = m.p_start[i]
    k = m.p_count[i]
    cnt = ti.Vector([0] * VOXELS, dt=ti.i32)
    evidence = ti.Vector([0] * VOXELS, dt=ti.i32)
    for j in range(s, s + k):
        c = code[perm[j]]
        q = c % EVIDENCE
        cnt[q] += 1
        evidence[q] |= c // EVIDENCE
    kept = 0
    layers = 0
    offset = s
    for v in range(VOXELS):       # (voxel index: z slowest, LEAF^2 voxels per layer)
        n_v = cnt[v]
        if n_v >= min_points and evidence[v]:
            kept += 1
        if v % (LEAF * LEAF) == LEAF * LEAF - 1:
            layers |= kept << (LAYER_BITS * (v // (LEAF * LEAF)))
        cnt[v] = offset
        offset += n_v
    for j in range(s, s + k):
        n = perm[j]
        q = code[n] % EVIDENCE
        perm2[cnt[q]] = n
        cnt[q] += 1
    return layers


@ti.func
def mark_near(m: ti.template(), i, stamp, reach_blk):
    """Mark the coarse `near` cells of every block within reach_blk of table cell i (the map
    blocks the kernel update visits); the table's margin (Mapper) keeps them inside it."""
    lo = m.near_index(i - reach_blk)
    hi = m.near_index(i + reach_blk)
    for nx in range(lo[0], hi[0] + 1):
        for ny in range(lo[1], hi[1] + 1):
            for nz in range(lo[2], hi[2] + 1):
                m.near[nx, ny, nz] = stamp


@ti.kernel
def sort_blocks(m: ti.template(), min_points: ti.i32,
                blocks: ti.types.ndarray(dtype=ti.i32, ndim=1),    # (B,) occupied cells
                code: ti.types.ndarray(dtype=ti.i32, ndim=1),      # (N,) rasterize's codes
                perm: ti.types.ndarray(dtype=ti.i32, ndim=1),      # (N,) points by block
                perm2: ti.types.ndarray(dtype=ti.i32, ndim=1)):    # (N,) out: by voxel
    """Sort every occupied block's points by voxel and count its training rows (b_layers)."""
    for b in range(blocks.shape[0]):
        i = m.cell_of_id(blocks[b])
        m.b_layers[i] = sort_block(m, i, min_points, code, perm, perm2)


@ti.kernel
def write_training(m: ti.template(), center: ti.types.vector(3, ti.i32), stamp: ti.i32,
                   reach_blk: ti.i32, t: ti.f32, min_points: ti.i32, unit_weight: ti.i32,
                   ell_min: ti.f32, adaptive: ti.i32, counting: ti.i32,
                   pts: ti.types.ndarray(dtype=ti.f32, ndim=2),       # (N, 3) sensor frame
                   label: ti.types.ndarray(dtype=ti.i32, ndim=1),     # (N,) train ids, or
                   prob: ti.types.ndarray(dtype=ti.f32, ndim=2),      # (N, C)
                   use_probs: ti.template(),
                   R: ti.types.matrix(3, 3, ti.f32), tr: ti.types.vector(3, ti.f32),
                   blocks: ti.types.ndarray(dtype=ti.i32, ndim=1),    # (B,) occupied cells
                   code: ti.types.ndarray(dtype=ti.i32, ndim=1),      # (N,) rasterize's codes
                   perm2: ti.types.ndarray(dtype=ti.i32, ndim=1),     # (N,) points by voxel
                   out_xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),    # (K, 3) centroid, local m
                   out_hist: ti.types.ndarray(dtype=ti.f32, ndim=2),   # (K, C) class evidence
                   out_classes: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (K,) bit c: evidence
                   out_single: ti.types.ndarray(dtype=ti.i32, ndim=1)  # (K,) the one class or 0
                   ):
    """Write every occupied block's training rows into its slice, mark the map voxels they
    update and the coarse cells near them."""
    center_blk = ti.floor(center / LEAF, ti.i32)
    base = center_blk - ti.Vector(m.table_half)     # world block of table cell 0
    for b in range(blocks.shape[0]):
        i = m.cell_of_id(blocks[b])
        if rows_to(m.b_layers[i], LEAF - 1) > 0:
            mark_near(m, i, stamp, reach_blk)
            write_block(m, i, base + i, m.b_start[i], t, min_points, unit_weight, ell_min,
                        adaptive, counting, pts, label, prob, use_probs, R, tr, code, perm2,
                        out_xyz, out_hist, out_classes, out_single)


@ti.func
def write_block(m: ti.template(), i, world_blk, slot, t, min_points, unit_weight, ell_min,
                adaptive, counting, pts: ti.template(), label: ti.template(),
                prob: ti.template(), use_probs: ti.template(), R, tr, code: ti.template(),
                perm2: ti.template(), out_xyz: ti.template(), out_hist: ti.template(),
                out_classes: ti.template(), out_single: ti.template()):
    """Sum each voxel's run of points (perm2, sorted by voxel) and write the kept ones' rows
    from `slot` on."""
    s = m.p_start[i]
    end = s + m.p_count[i]
    npts = 0
    evidence = 0
    # coordinates are summed relative to the voxel's first point: offsets below a voxel's size
    # keep float32 sums of thousands of points exact to ~1e-6 m, far from the origin too
    first = ti.Vector([0.0, 0.0, 0.0])
    xyz_sum = ti.Vector([0.0, 0.0, 0.0])
    h = ti.Vector([0.0] * m.C)
    for j in range(s, end):
        n = perm2[j]
        c = code[n]
        q = c % EVIDENCE
        x = to_local(R, ti.Vector([pts[n, 0], pts[n, 1], pts[n, 2]]), tr)
        if npts == 0:
            first = x
        npts += 1
        evidence |= c // EVIDENCE
        xyz_sum += x - first
        if ti.static(use_probs):
            for k in ti.static(range(1, m.C)):
                h[k] += prob[n, k]
        elif label[n] > 0:     # train id 0 (unlabeled) counts as a point but adds no evidence
            h[label[n]] += 1.0
        next_q = -1
        if j + 1 < end:
            next_q = code[perm2[j + 1]] % EVIDENCE
        if next_q != q:        # the voxel's last point
            if npts >= min_points and evidence:
                u = m.wrap(world_blk * LEAF + local_of_index(q))
                write_row(m, u, slot, first + xyz_sum / ti.cast(npts, ti.f32), h, t, unit_weight,
                          ell_min, adaptive, counting, out_xyz, out_hist, out_classes,
                          out_single)
                slot += 1
            npts = 0
            evidence = 0
            xyz_sum = ti.Vector([0.0, 0.0, 0.0])
            h = ti.Vector([0.0] * m.C)


@ti.func
def write_row(m: ti.template(), u, slot, centroid, hist, t, unit_weight, ell_min, adaptive,
              counting, out_xyz: ti.template(), out_hist: ti.template(),
              out_classes: ti.template(), out_single: ti.template()):
    """Training row `slot` for map voxel u, and u's mark for the kernel update."""
    h = hist
    if unit_weight:
        h *= 1.0 / h.sum()
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
        m.ell[u] = ell_min                  # (any positive length: a live voxel)
        fuse_voxel(m, u, h, t, 0.0)
    elif adaptive:
        # the length needs the voxel's counters, which the kernel update reads anyway (one
        # pass over the map instead of two): it computes the length from the row (exact in
        # float32 up to 2^24 rows)
        m.ell[u] = -ti.cast(slot + 1, ti.f32)
    else:
        m.ell[u] = ell_min
    # u is live from now on: ell is not on the bitmasked node, so a store to a field that is
    # sets the voxel's bit (t_last keeps its value; a free cell holds 0). Not ti.activate: in
    # taichi 1.7.4 it leaves the bit clear when it has to allocate the block first (caught by
    # tests/test_kernels.py), and it warns about int32 indices at every compile
    m.t_last[u] = m.t_last[u]
