"""Steps 1-2 of the method, first half: transform, range-check and sort a scan's points by
leaf block.

Each point is moved to local map coordinates, dropped if outside the range / height band or the
live window (checked *before* any field is indexed: Taichi does not check indices in release
mode), and otherwise counted in its leaf block's cell of the scan's dense table; a counting sort
then lists every block's points together (`perm`). kernels/training.py sorts each block's
points by voxel and reduces them to the voxels' histograms, counts and centroids.

Sorting costs two integer atomics per point on a dense table, where a sparse tree of per-voxel
histograms would pay about ten sparse activations and float atomics per point, and a reset of
every voxel after the scan.
Non-finite points never get here: the mapper moves them out of range first (fast math makes
NaN tests unreliable).
"""

import functools

import taichi as ti
from tisem.kernels.layout import LEAF, block_and_local
from tisem.kernels.params import ScanParams

# what happened to a point (locate), and the slots of the counts the locate kernel returns (the
# last one: how many leaf blocks the kept points fall in)
USED, OUT_OF_RANGE, OUT_OF_WINDOW, IMPLAUSIBLY_FAR, OUT_OF_BAND, BLOCKS = 0, 1, 2, 3, 4, 5
CORRUPT_RANGE_M = 1000.0  # no LiDAR returns from this far: such points are corrupt data
EVIDENCE = LEAF**3  # bit of a point's voxel code: the point carries class evidence
DROPPED = -1  # a point's cell when it is not used


def evidence_array(use_probs: bool):
    """The kernel argument type of a scan's class evidence: (N,) int32 train ids in [0, C), or
    (N, C) float32 probabilities (class 0, unlabeled, is never evidence)."""
    if use_probs:
        return ti.types.ndarray(dtype=ti.f32, ndim=2)
    return ti.types.ndarray(dtype=ti.i32, ndim=1)


@ti.func
def to_local(R, p, translation):
    """Sensor frame -> local map coordinates (the one place this arithmetic is written):
    R_local_sensor @ p + the sensor's position."""
    return R @ p + translation


@ti.func
def locate(p, s: ti.template()):
    """What becomes of sensor-frame point p (USED, OUT_OF_RANGE, OUT_OF_BAND: in range but
    outside the height band, OUT_OF_WINDOW or IMPLAUSIBLY_FAR, a kind of out of range), and its
    world voxel."""
    fate = USED
    q = to_local(s.rotation, p, s.translation_m)
    w = ti.floor(q * s.inv_resolution, ti.i32)
    r2 = p.dot(p)
    if r2 < s.min_range2_m2 or r2 > s.max_range2_m2:
        fate = IMPLAUSIBLY_FAR if r2 > CORRUPT_RANGE_M * CORRUPT_RANGE_M else OUT_OF_RANGE
    elif p[2] < s.min_z_m or p[2] > s.max_z_m:
        fate = OUT_OF_BAND
    else:
        off = ti.abs(w - s.center_vox)
        limit = s.limit_vox
        if off[0] > limit[0] or off[1] > limit[1] or off[2] > limit[2]:
            fate = OUT_OF_WINDOW
    return fate, w


@ti.func
def has_evidence(num_classes: ti.template(), evidence: ti.template(), n, use_probs: ti.template()):
    """Whether point n adds class evidence (train id 0 / class 0 never does)."""
    ev = 0
    if ti.static(use_probs):
        for c in ti.static(range(1, num_classes)):
            if evidence[n, c] > 0:
                ev = 1
    elif evidence[n] > 0:
        ev = 1
    return ev


@functools.cache
def locate_kernel(use_probs: bool):
    """The kernel that locates a scan's points, for labels or probabilities as evidence."""

    @ti.kernel
    def locate_points(
        m: ti.template(),
        s: ScanParams,
        pts: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (N, k >= 3) sensor frame: x y z first
        evidence: evidence_array(use_probs),  # (N,) or (N, C)
        cell: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) out: table cell id
        code: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) out: voxel in block
        blocks: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) out: occupied cells
    ) -> ti.types.vector(6, ti.i32):
        """Count every kept point in its block's cell (p_count), list the cells that get points
        (`blocks`, in no particular order) and widen their columns' z-ranges.

        Writes each point's cell id (DROPPED if not kept) and its voxel's index in the block,
        plus EVIDENCE if the point carries class evidence. Returns the number of points per fate
        (index USED, OUT_OF_RANGE, OUT_OF_BAND, ...; implausibly far points are also counted as
        out of range) and, at index BLOCKS, the number of occupied cells.
        """
        m.counter[None] = 0
        # kernel-scope counters: Taichi keeps them per thread and adds them up at the end, where
        # one shared atomic counter per point made the two threads fight over a cache line
        out_of_range = 0
        out_of_band = 0
        out_of_window = 0
        far = 0
        center_blk = ti.floor(s.center_vox / LEAF, ti.i32)
        for n in range(pts.shape[0]):
            p = ti.Vector([pts[n, 0], pts[n, 1], pts[n, 2]])
            fate, w = locate(p, s)
            cell[n] = DROPPED
            if fate == OUT_OF_RANGE:
                out_of_range += 1
            elif fate == IMPLAUSIBLY_FAR:
                out_of_range += 1
                far += 1
            elif fate == OUT_OF_BAND:
                out_of_band += 1
            elif fate == OUT_OF_WINDOW:
                out_of_window += 1
            else:
                blk, q = block_and_local(w)
                # inside the table: the point is within limit_vox of the sensor (MapGeometry)
                i, _ = m.table_index(blk, center_blk)
                cell[n] = m.cell_id(i)
                code[n] = q + EVIDENCE * has_evidence(m.C, evidence, n, use_probs)
                if ti.atomic_add(m.p_count[i], 1) == 0:  # the block's first point
                    blocks[ti.atomic_add(m.counter[None], 1)] = cell[n]
                    ti.atomic_min(m.col_lo[i[0], i[1]], i[2])
                    ti.atomic_max(m.col_hi[i[0], i[1]], i[2])
        return ti.Vector(
            [
                pts.shape[0] - out_of_range - out_of_band - out_of_window,
                out_of_range,
                out_of_window,
                far,
                out_of_band,
                m.counter[None],
            ]
        )

    return locate_points


@functools.cache
def scatter_kernel(in_order: bool):
    """The kernel that lists every kept point in its block's slice (table.column_slots gave
    the slices, and restarted p_count as the fill cursor that this counts back up).

    `in_order` (CPUs): one thread, each block's points in the scan's order, so that a voxel's
    points are summed in the same order whatever the threads (and on two threads no slower
    than the atomic cursors, whose cache lines the threads fought over). Otherwise (GPUs) a
    thread per point with atomic cursors: a block's points in the order the threads come,
    which moves a centroid or evidence sum by float rounding from run to run."""

    @ti.kernel
    def scatter_points(
        m: ti.template(),
        cell: ti.types.ndarray(dtype=ti.i32, ndim=1),
        perm: ti.types.ndarray(dtype=ti.i32, ndim=1),
    ):  # (N,) out: points by block
        ti.loop_config(serialize=in_order)
        for n in range(cell.shape[0]):
            if cell[n] != DROPPED:
                i = m.cell_of_id(cell[n])
                perm[m.p_start[i] + ti.atomic_add(m.p_count[i], 1)] = n

    return scatter_points
