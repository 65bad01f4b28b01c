"""Steps 1-2 of the method: transform, range-check and rasterise a scan into the scan layer.

Each point is moved to local map coordinates, dropped if outside the range / height band or the
live window (checked *before* any field is indexed: Taichi does not check indices in release
mode), and otherwise added to its voxel's histogram, count and coordinate sum. Non-finite points
never get here: the mapper moves them out of range first (fast math makes NaN tests unreliable).
"""
import taichi as ti

from kernels.layout import LEAF

# what happened to a point (locate), and the slots of rasterize's returned counts
USED, OUT_OF_RANGE, OUT_OF_WINDOW, IMPLAUSIBLY_FAR = 0, 1, 2, 3
FAR_M = 1000.0   # no LiDAR returns from this far: such points are corrupt data, not range


@ti.func
def to_local(R, p, t):
    """Sensor frame -> local map coordinates (the one place this arithmetic is written)."""
    return R @ p + t


@ti.func
def locate(p, R, t, center, limit, min_r2, max_r2, min_z, max_z, inv_res):
    """What becomes of sensor-frame point p (USED, OUT_OF_RANGE, OUT_OF_WINDOW or
    IMPLAUSIBLY_FAR, a kind of out of range), its world voxel and its local coordinates."""
    fate = USED
    q = to_local(R, p, t)
    w = ti.floor(q * inv_res, ti.i32)
    r2 = p.dot(p)
    if r2 < min_r2 or r2 > max_r2 or p[2] < min_z or p[2] > max_z:
        fate = IMPLAUSIBLY_FAR if r2 > FAR_M * FAR_M else OUT_OF_RANGE
    else:
        off = ti.abs(w - center)
        if off[0] > limit[0] or off[1] > limit[1] or off[2] > limit[2]:
            fate = OUT_OF_WINDOW
    return fate, w, q


@ti.func
def add_point(m: ti.template(), w, q, center, min_points):
    """Add a point to its voxel; the point that brings the voxel to `min_points` counts the
    voxel in its leaf block's slot of the training table (step 3's filter, kernels/training.py:
    exactly one point sees that count, so no separate pass over the voxels is needed)."""
    u = m.s_wrap(w)
    if ti.atomic_add(m.s_npts[u], 1) == min_points - 1:
        center_blk = ti.floor(center / LEAF, ti.i32)
        i, _ = m.table_index(ti.floor(w / LEAF, ti.i32), center_blk)
        ti.atomic_add(m.b_count[i], 1)
        ti.atomic_add(m.col_count[i[0], i[1]], 1)
    for a in ti.static(range(3)):
        m.s_sum[u, a] += q[a]
    return u


@ti.kernel
def rasterize(m: ti.template(),
              pts: ti.types.ndarray(dtype=ti.f32, ndim=2),       # (N, 3) sensor frame
              label: ti.types.ndarray(dtype=ti.i32, ndim=1),     # (N,) train id in [0, C), or
              prob: ti.types.ndarray(dtype=ti.f32, ndim=2),      # (N, C), class 0 ignored
              use_probs: ti.template(),                          # which of the two is evidence
              R: ti.types.matrix(3, 3, ti.f32), t: ti.types.vector(3, ti.f32),
              center: ti.types.vector(3, ti.i32), limit: ti.types.vector(3, ti.i32),
              min_r2: ti.f32, max_r2: ti.f32, min_z: ti.f32, max_z: ti.f32, inv_res: ti.f32,
              min_points: ti.i32) -> ti.types.vector(4, ti.i32):
    """Returns the number of points per fate (index USED, OUT_OF_RANGE, ...); implausibly far
    points are also counted as out of range."""
    # kernel-scope counters: Taichi keeps them per thread and adds them up at the end, where
    # one shared atomic counter per point made the two threads fight over a cache line
    out_of_range = 0
    out_of_window = 0
    far = 0
    for n in range(pts.shape[0]):
        p = ti.Vector([pts[n, 0], pts[n, 1], pts[n, 2]])
        fate, w, q = locate(p, R, t, center, limit, min_r2, max_r2, min_z, max_z, inv_res)
        if fate == OUT_OF_RANGE:
            out_of_range += 1
        elif fate == IMPLAUSIBLY_FAR:
            out_of_range += 1
            far += 1
        elif fate == OUT_OF_WINDOW:
            out_of_window += 1
        else:
            u = add_point(m, w, q, center, min_points)
            if ti.static(use_probs):
                for c in ti.static(range(1, m.C)):
                    if prob[n, c] > 0:
                        m.s_hist[u, c] += prob[n, c]
            elif label[n] > 0:  # train id 0 (unlabeled) counts as a point but adds no evidence
                m.s_hist[u, label[n]] += 1.0
    return ti.Vector([pts.shape[0] - out_of_range - out_of_window, out_of_range, out_of_window, far])


@ti.kernel
def free_idle_blocks(m: ti.template(), stamp: ti.i32):
    """Free the scan-layer blocks the scan with `stamp` did not use (their voxels were reset
    when last used; freeing recycles the memory zero-filled).

    The blocks the scan used stay allocated for the next scans, which mostly hit the same
    ones again. Top cells stay too: they are at most (scan extent / 32)^3 cells of 4 KB.
    """
    for B in ti.grouped(m.s_stamp):
        if m.s_stamp[B] != stamp:
            ti.deactivate(m.s_blk, ti.cast(B, ti.i32))
