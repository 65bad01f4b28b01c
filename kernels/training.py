"""Steps 2-3, second half: reduce each leaf block's points (sorted by block in
kernels/rasterize.py) to its voxels, filter them, and write the training points (centroid +
class evidence) sorted by block.

Three passes, none with float atomics: `sort_blocks`, one task per occupied leaf block, sorts
the block's points by voxel (a counting sort over its 64 voxels) and counts the voxels that pass
the filter (`voxel_kept`) per z layer; `table.column_slots` hands out the rows in table order,
a column's blocks one after another in z, so that any z-range of a column is one contiguous
slice (kernels/bki.py); the training kernel, one task per block again, sums each kept voxel's
run of points into its row. Tasks per block rather than per column keep thousands of them busy
on a GPU.

None of this touches the map: the next steps find each row's map voxel from the row's block and
its voxel index in the block (`visit_training_voxels`).
"""

import functools

import taichi as ti
from tisem.kernels.layout import LAYER_BITS, LEAF, local_of_index, rows_to
from tisem.kernels.params import ScanParams
from tisem.kernels.rasterize import EVIDENCE, evidence_array, to_local

from tisem.class_centroids import SLOT

VOXELS = LEAF**3


@ti.func
def voxel_kept(n_points, evidence, min_points):
    """Step 3, the redundant-voxel filter: 1 for a voxel with at least `min_points` points and
    some class evidence (a point with a train id > 0), else 0."""
    kept = 0
    if n_points >= min_points and evidence:
        kept = 1
    return kept


@ti.func
def sort_block(
    m: ti.template(), i, min_points, code: ti.template(), perm: ti.template(), perm2: ti.template()
):
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
    for v in range(VOXELS):  # (voxel index: z slowest, LEAF^2 voxels per layer)
        n_v = cnt[v]
        kept += voxel_kept(n_v, evidence[v], min_points)
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


@ti.kernel
def sort_blocks(
    m: ti.template(),
    min_points: ti.i32,
    blocks: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (B,) occupied cells
    code: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) rasterize's codes
    perm: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) points by block
    perm2: ti.types.ndarray(dtype=ti.i32, ndim=1),
):  # (N,) out: by voxel
    """Sort every occupied block's points by voxel and count its training rows (b_layers)."""
    for b in range(blocks.shape[0]):
        i = m.cell_of_id(blocks[b])
        m.b_layers[i] = sort_block(m, i, min_points, code, perm, perm2)


@ti.func
def top_two(h, num_classes: ti.template()):
    """(c1, c2): the two classes with the most evidence in histogram h (classes 1..C-1, the
    lower class first on a tie); c2 = 0 when h has evidence for one class only."""
    c1 = 0
    c2 = 0
    v1 = 0.0
    v2 = 0.0
    for c in ti.static(range(1, num_classes)):
        if h[c] > v1:
            c2 = c1
            v2 = v1
            c1 = c
            v1 = h[c]
        elif h[c] > v2:
            c2 = c
            v2 = h[c]
    return c1, c2


@functools.cache
def training_kernel(unit_weight: bool, use_probs: bool, centroids: bool = False):
    """The kernel that writes the training rows, for a point weighting and a kind of evidence;
    `centroids`: also each row's class centroids (kernels/centroids.py)."""

    @ti.kernel
    def write_training(
        m: ti.template(),
        s: ScanParams,
        pts: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (N, k >= 3) sensor frame: x y z first
        evidence: evidence_array(use_probs),  # (N,) or (N, C)
        blocks: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (B,) occupied cells
        code: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) voxel codes
        perm2: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) points by voxel
        out_xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (K, 3) centroid, local
        out_hist: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (K, C) class evidence
        out_classes: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (K,) bit c: evidence
        out_single: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (K,) the class or 0
        out_voxel: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (K,) voxel in block
        out_cent: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (K, CENTROID_COLS) with centroids
    ):
        """Write every occupied block's training rows into its slice."""
        base = ti.floor(s.center_vox / LEAF, ti.i32) - ti.Vector(m.table_half)  # cell 0's block
        for b in range(blocks.shape[0]):
            i = m.cell_of_id(blocks[b])
            if rows_to(m.b_layers[i], LEAF - 1) > 0:
                write_block(
                    m,
                    s,
                    i,
                    m.b_start[i],
                    pts,
                    evidence,
                    code,
                    perm2,
                    out_xyz,
                    out_hist,
                    out_classes,
                    out_single,
                    out_voxel,
                    (base + i) * LEAF,
                    out_cent,
                )

    @ti.func
    def write_row_centroids(
        m: ti.template(),
        s: ti.template(),
        slot,
        run,
        last,
        corner,
        hist,
        centroid,
        npts,
        pts: ti.template(),
        evidence: ti.template(),
        perm2: ti.template(),
        out_cent: ti.template(),
    ):
        """Row `slot`'s class centroids: its voxel's two leading classes in this scan (from
        `hist`) and the mean offset of their points (perm2[run..last]) from the voxel's low
        corner `corner`, in metres; a second pass over the run, once its histogram has told
        which classes lead, unless every point of the voxel has the one class (most voxels):
        then that class's points are all the voxel's, and their mean its `centroid`."""
        R = s.rotation
        tr = s.translation_m
        c1, c2 = top_two(hist, m.C)
        alone = False
        if ti.static(not use_probs):
            alone = c2 == 0 and hist[c1] == ti.cast(npts, ti.f32)
        for r in ti.static(range(2)):
            cr = c1 if r == 0 else c2
            w_sum = 0.0
            x_sum = ti.Vector([0.0, 0.0, 0.0])
            if alone and r == 0:
                w_sum = hist[c1]
                x_sum = (centroid - corner) * w_sum
            elif cr > 0:
                for j in range(run, last + 1):
                    n = perm2[j]
                    w = 0.0
                    if ti.static(use_probs):
                        w = evidence[n, cr]
                    elif evidence[n] == cr:
                        w = 1.0
                    if w > 0:
                        x = to_local(R, ti.Vector([pts[n, 0], pts[n, 1], pts[n, 2]]), tr)
                        w_sum += w
                        x_sum += w * (x - corner)
            if w_sum > 0:
                x_sum /= w_sum
            out_cent[slot, r * SLOT] = ti.cast(cr, ti.f32)
            out_cent[slot, r * SLOT + 1] = w_sum
            for a in ti.static(range(3)):
                out_cent[slot, r * SLOT + 2 + a] = x_sum[a]

    @ti.func
    def write_block(
        m: ti.template(),
        s: ti.template(),
        i,
        slot,
        pts: ti.template(),
        evidence: ti.template(),
        code: ti.template(),
        perm2: ti.template(),
        out_xyz: ti.template(),
        out_hist: ti.template(),
        out_classes: ti.template(),
        out_single: ti.template(),
        out_voxel: ti.template(),
        corner_vox,
        out_cent: ti.template(),
    ):
        """Sum each voxel's run of points (perm2, sorted by voxel) and write the kept ones' rows
        from `slot` on (`corner_vox`: the block's first world voxel, for the centroids)."""
        # the pose copied once per block, outside the loop over points: where the compiler finds
        # these values decides how fast math associates R @ p + t (keeping the map bitwise
        # stable across refactorings, not only within float tolerance)
        R = s.rotation
        tr = s.translation_m
        start = m.p_start[i]
        end = start + m.p_count[i]
        npts = 0
        has_evidence = 0
        # coordinates are summed relative to the voxel's first point: offsets below a voxel's
        # size keep float32 sums of thousands of points exact to ~1e-6 m, far from the origin
        first = ti.Vector([0.0, 0.0, 0.0])
        xyz_sum = ti.Vector([0.0, 0.0, 0.0])
        h = ti.Vector([0.0] * m.C)
        run = start  # the voxel's first point in perm2
        for j in range(start, end):
            n = perm2[j]
            c = code[n]
            q = c % EVIDENCE
            x = to_local(R, ti.Vector([pts[n, 0], pts[n, 1], pts[n, 2]]), tr)
            if npts == 0:
                first = x
            npts += 1
            has_evidence |= c // EVIDENCE
            xyz_sum += x - first
            if ti.static(use_probs):
                for k in ti.static(range(1, m.C)):
                    h[k] += evidence[n, k]
            elif evidence[n] > 0:  # train id 0 (unlabeled) counts as a point, adds no evidence
                h[evidence[n]] += 1.0
            next_q = -1
            if j + 1 < end:
                next_q = code[perm2[j + 1]] % EVIDENCE
            if next_q != q:  # the voxel's last point
                if voxel_kept(npts, has_evidence, s.min_points):
                    centroid = first + xyz_sum / ti.cast(npts, ti.f32)
                    write_training_row(
                        m,
                        slot,
                        q,
                        centroid,
                        h,
                        out_xyz,
                        out_hist,
                        out_classes,
                        out_single,
                        out_voxel,
                    )
                    if ti.static(centroids):
                        corner = (corner_vox + local_of_index(q)).cast(ti.f32) * s.resolution_m
                        write_row_centroids(
                            m,
                            s,
                            slot,
                            run,
                            j,
                            corner,
                            h,
                            centroid,
                            npts,
                            pts,
                            evidence,
                            perm2,
                            out_cent,
                        )
                    slot += 1
                run = j + 1
                npts = 0
                has_evidence = 0
                xyz_sum = ti.Vector([0.0, 0.0, 0.0])
                h = ti.Vector([0.0] * m.C)

    @ti.func
    def write_training_row(
        m: ti.template(),
        slot,
        voxel,
        centroid,
        hist,
        out_xyz: ti.template(),
        out_hist: ti.template(),
        out_classes: ti.template(),
        out_single: ti.template(),
        out_voxel: ti.template(),
    ):
        """Training row `slot`: the voxel's centroid, its (weighted) class evidence, which
        classes that has, and the voxel's index in its block."""
        h = hist
        if ti.static(unit_weight):
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
        out_voxel[slot] = voxel

    return write_training


@ti.kernel
def visit_training_voxels(
    m: ti.template(),
    s: ScanParams,
    blocks: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (B,) occupied cells
    voxel: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (K,) voxel in block
    hist: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (K, C) evidence
    visit_block: ti.template(),
    visit_row: ti.template(),
):
    """For every occupied block with training rows, visit_block(m, s, i) with its table cell i,
    then visit_row(m, s, u, row, hist) for each of its rows with the row's map voxel u
    (storage index). One task per block: a block's rows are distinct voxels."""
    base = ti.floor(s.center_vox / LEAF, ti.i32) - ti.Vector(m.table_half)  # cell 0's block
    for b in range(blocks.shape[0]):
        i = m.cell_of_id(blocks[b])
        rows = rows_to(m.b_layers[i], LEAF - 1)
        if rows > 0:
            visit_block(m, s, i)
            first = m.b_start[i]
            for row in range(first, first + rows):
                u = m.wrap((base + i) * LEAF + local_of_index(voxel[row]))
                visit_row(m, s, u, row, hist)
