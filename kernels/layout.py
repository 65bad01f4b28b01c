"""The one module that knows the SNode tree.

Two sparse trees of the same shape, indexed by *storage* voxel index u in [0, N):

    root.pointer(top cells) -> pointer(8^3 leaf blocks) -> bitmasked(4^3 voxels) -> dense(l, C)

* the map layer: semantic counters sigma[u, c], last-update time t_last[u], kernel length ell[u];
* the scan layer (cleared after every scan): the scan's class histogram, point count and
  coordinate sums per voxel, and the kernel-weighted evidence delta[u, c] of the scan.

Why this shape (measured in shared/notes/taichi-sparse.md): a small two-level pointer top keeps
struct-fors cheap, 4^3 bitmasked leaves suit surface-like LiDAR data, and the class axis as an
inner dense(l, C) of a 4-D scalar field needs one atomic per label (and avoids the 1.7.x crash of
vector-component atomics). Struct-fors run over the 3-D fields placed on the leaf, never the 4-D.

Storage is toroidal: world voxel w (int32, relative to the mapper's origin) lives at
u = w & (N - 1). The mapper keeps every live block inside a window smaller than N/2 around the
sensor, so two live world voxels never share a storage cell, and a storage index is turned back
into its world index by unwrapping around the window centre (`unwrap`).
"""

import taichi as ti

LEAF = 4   # voxels per leaf block edge
MID = 8    # leaf blocks per top cell edge
TOP = LEAF * MID
KERNEL_TABLE = 4096   # samples of the sparse kernel over r^2 in [0, 1]
NEAR = 2   # table cells (leaf blocks) per edge of a cell of the coarse `near` table


def _pow2_at_least(n: int) -> int:
    p = TOP
    while p < n:
        p *= 2
    return p


def storage_extent(window_half_vox: tuple[int, int, int]) -> tuple[int, int, int]:
    """Power-of-two storage extent per axis that holds a window of the given half-size
    plus one top cell of slack on each side without aliasing."""
    return tuple(_pow2_at_least(2 * (h + 2 * TOP) + 1) for h in window_half_vox)


@ti.data_oriented
class MapFields:
    """The Taichi fields of one map. Create after `ti.init`; never share across inits."""

    def __init__(self, num_classes: int, extent: tuple[int, int, int],
                 scan_extent: tuple[int, int, int], table_half: tuple[int, int, int]):
        for n in (*extent, *scan_extent):
            if n % TOP or n & (n - 1):
                raise ValueError(f"storage extents {extent}, {scan_extent} must be powers of two "
                                 f">= {TOP}")
        self.C = int(num_classes)
        self.N = tuple(int(n) for n in extent)
        self.mask = tuple(n - 1 for n in self.N)
        self.N_blk = tuple(n // LEAF for n in self.N)    # extent in leaf blocks
        self.N_top = tuple(n // TOP for n in self.N)     # extent in top cells
        top_shape = tuple(n // TOP for n in self.N)
        # the scan layer only ever holds one scan around the sensor: its own, smaller toroidal
        # extent keeps the root that every struct-for over it scans small
        self.NS = tuple(int(n) for n in scan_extent)
        self.NS_blk = tuple(n // LEAF for n in self.NS)
        # one SNode tree per map, built and finalised here
        fb = ti.FieldsBuilder()

        # map layer: ~88 B per active voxel (20 x f32 counters, t_last, ell) + bitmask
        self.counts = ti.field(ti.f32)
        self.t_last = ti.field(ti.f32)
        # > 0 for every active voxel (doubles as the activity test); while a scan is fused,
        # -(1 + the voxel's row in the scan's training arrays) for a voxel the scan hit in an
        # adaptive mode: kernels/training.py writes that, kernels/bki.py turns it into the length
        self.ell = ti.field(ti.f32)
        self.top = fb.pointer(ti.ijk, top_shape)
        self.blk = self.top.pointer(ti.ijk, MID)
        self.vox = self.blk.bitmasked(ti.ijk, LEAF)
        self.vox.dense(ti.l, self.C).place(self.counts)
        self.vox.place(self.t_last, self.ell)

        # scan layer: per voxel the scan's histogram, coordinate sum and point count
        self.s_hist = ti.field(ti.f32)
        self.s_sum = ti.field(ti.f32)
        self.s_npts = ti.field(ti.i32)
        self.s_top = fb.pointer(ti.ijk, tuple(n // TOP for n in self.NS))
        self.s_blk = self.s_top.pointer(ti.ijk, MID)
        self.s_vox = self.s_blk.bitmasked(ti.ijk, LEAF)
        self.s_vox.dense(ti.l, self.C).place(self.s_hist)
        self.s_vox.dense(ti.l, 3).place(self.s_sum)
        self.s_vox.place(self.s_npts)
        # the last scan that used each scan-layer block: a block is reset voxel by voxel after
        # use and kept while scans keep hitting it, as freeing one costs a 6 KB zero-fill
        self.s_stamp = ti.field(ti.i32)
        self.s_blk.place(self.s_stamp)

        # the scan's training points per leaf block (count, first slot in the block-sorted
        # arrays): a dense table centred on the sensor, since the kernel update looks these up
        # tens of times per voxel and a dense read is several times cheaper than a sparse one
        self.table_half = tuple(int(h) for h in table_half)
        self.b_count = ti.field(ti.i32)
        self.b_start = ti.field(ti.i32)
        fb.dense(ti.ijk, tuple(2 * h + 1 for h in self.table_half)).place(self.b_count, self.b_start)
        # training voxels per (x, y) column of the table: assign_slots lays each column's blocks
        # out one after another in z, so the kernel update reads a column's z-range of blocks
        # as one contiguous slice instead of one slice per block
        self.col_count = ti.field(ti.i32)
        fb.dense(ti.ij, tuple(2 * h + 1 for h in self.table_half[:2])).place(self.col_count)
        # which map blocks the scan's kernels can reach: per NEAR x NEAR x NEAR table cells, the
        # last scan with a training block within reach (kernels/training.py marks it). A dense
        # read per map block replaces a sparse is_active test per (training block, neighbour).
        self.near = ti.field(ti.i32)
        fb.dense(ti.ijk, tuple(2 * h // NEAR + 1 for h in self.table_half)).place(self.near)

        self.counter = ti.field(ti.i32)
        fb.place(self.counter)
        self.kernel_lut = ti.field(ti.f32)  # g(r) sampled in r^2 (kernels/bki.py)
        fb.dense(ti.i, KERNEL_TABLE + 1).place(self.kernel_lut)
        self._tree = fb.finalize()

    @ti.func
    def in_table(self, i):
        return (0 <= i[0] <= 2 * self.table_half[0] and 0 <= i[1] <= 2 * self.table_half[1]
                and 0 <= i[2] <= 2 * self.table_half[2])

    @ti.func
    def near_index(self, i):
        """Cell of the coarse `near` table holding training-table cell i (inside the table)."""
        return i // NEAR

    @ti.func
    def table_index(self, world_blk, center_blk):
        """(index into b_count / b_start, whether the block lies inside the table)."""
        i = world_blk - center_blk + ti.Vector(self.table_half)
        return i, self.in_table(i)

    @ti.func
    def _wrap(self, w, n: ti.template()):
        return ti.Vector([w[0] & (n[0] - 1), w[1] & (n[1] - 1), w[2] & (n[2] - 1)])

    @ti.func
    def unwrap_cells(self, u, center, n: ti.template()):
        """Storage index -> the world index nearest `center` (valid within n/2 of it)."""
        w = ti.Vector([0, 0, 0])
        for a in ti.static(range(3)):
            d = (u[a] - center[a]) & (n[a] - 1)
            if d >= n[a] // 2:
                d -= n[a]
            w[a] = center[a] + d
        return w

    @ti.func
    def wrap(self, w):
        """World voxel -> map storage voxel."""
        return self._wrap(w, self.N)

    @ti.func
    def wrap_blk(self, b):
        """World leaf block -> map storage leaf block."""
        return self._wrap(b, self.N_blk)

    @ti.func
    def unwrap(self, u, center):
        """Map storage voxel -> world voxel (nearest the window centre `center`)."""
        return self.unwrap_cells(u, center, self.N)

    @ti.func
    def unwrap_blk(self, b, center_blk):
        """Map storage leaf block -> world leaf block."""
        return self.unwrap_cells(b, center_blk, self.N_blk)

    @ti.func
    def s_wrap(self, w):
        """World voxel -> scan-layer storage voxel."""
        return self._wrap(w, self.NS)

    @ti.func
    def s_unwrap(self, u, center):
        """Scan-layer storage voxel -> world voxel (nearest the sensor's voxel `center`)."""
        return self.unwrap_cells(u, center, self.NS)

    @ti.func
    def s_unwrap_blk(self, b, center_blk):
        """Scan-layer storage leaf block -> world leaf block."""
        return self.unwrap_cells(b, center_blk, self.NS_blk)
