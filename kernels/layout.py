"""The one module that knows the SNode tree and the scan's table.

The map is one sparse tree indexed by *storage* voxel index u in [0, N):

    root.pointer(top cells) -> pointer(8^3 leaf blocks) -> bitmasked(4^3 voxels) -> dense(l, C)

holding the semantic counters sigma[u, c] (with compact_counters behind a pointer per voxel
beside the bitmask instead), the time of the last update t_last_rel[u], the kernel length
length[u] and, with free space only, the occupancy evidence (kernels/raycast.py).
A scan never touches a sparse node until its training points are known: its points are sorted
by leaf block in a dense table of the blocks around the sensor (kernels/rasterize.py,
kernels/training.py), which costs plain integer atomics instead of sparse activations.

Why this shape (measured on a 2-thread CPU): a small two-level pointer top keeps struct-fors
cheap (a one-level pointer over the whole window costs a dense root of 16 B per cell and seconds
per struct-for), 4^3 bitmasked leaves suit surface-like LiDAR data (~7 live voxels of a block's
64), and the class axis as an inner dense(l, C) of a 4-D scalar field needs one atomic per label
(taichi 1.7.x aborts on atomics into one component of a vector field). Struct-fors run over the
3-D fields placed on the leaf, never the 4-D one (that builds an element list per voxel).

Storage is toroidal: world voxel w (int32, relative to the mapper's origin) lives at
u = w & (N - 1). The mapper keeps every live block inside a window smaller than N/2 around the
sensor, so two live world voxels never share a storage cell, and a storage index is turned back
into its world index by unwrapping around the window centre (`unwrap`).
"""

import taichi as ti

from tisem.class_centroids import CENTROID_COLS

LEAF_BITS = 2
LEAF = 1 << LEAF_BITS  # voxels per leaf block edge
MID = 8  # leaf blocks per top cell edge
TOP = LEAF * MID
KERNEL_TABLE = 4096  # samples of the sparse kernel over r^2 in [0, 1]
CROSSED_CAPACITY = 1 << 16  # live voxels one scan's rays cross (7.9k on a real scan, 12 B each)
NEAR = 2  # table cells (leaf blocks) per edge of a cell of the coarse `near` table
LAYER_BITS = 8  # per z layer of a block in b_layers: up to 64 rows (LEAF^3 voxels)
EMPTY_LO = 1 << 30  # col_lo of a column without points (any z cell is below it)

# The scan's table (MapFields below) is dense: 16 B per cell in four int32 fields, plus the coarse
# `near` table (an eighth of an int32 per cell) and the per-column z-range, under 18 B in all.
TABLE_BYTES_PER_CELL = 18
MAX_TABLE_CELLS = 2**28  # cell ids are int32
MAX_REACH_BLK = 2  # the longest kernel, in leaf blocks, the table's margin is sized for
# A voxel's training row travels through float32 in its pending-length mark (exact below 2^24),
# and a scan has at most as many training voxels as points.
MAX_SCAN_POINTS = 2**24


def table_half_blocks(limit_vox, reach_blk: int) -> tuple[int, int, int]:
    """Half-size, in leaf blocks, of the scan's table for kept points within `limit_vox` of the
    sensor's voxel: every block a training voxel can fall in, plus the blocks a kernel of a
    voxel receiving an update reaches from there (the update reads the table around each)."""
    return tuple(-(-int(v) // LEAF) + 2 * int(reach_blk) + 3 for v in limit_vox)


@ti.func
def deactivate(snode: ti.template(), index):
    """ti.deactivate(snode, index) for a 3-D index, cast to int32 element by element: taichi
    1.7.4 prints "Field index N not int32, casting into int32 implicitly" when it compiles a
    deactivation by a vector or an ndarray row, int32 or not (on a fresh compile, e.g. at a
    user's first window move)."""
    ti.deactivate(
        snode,
        [ti.cast(index[0], ti.i32), ti.cast(index[1], ti.i32), ti.cast(index[2], ti.i32)],
    )


# A live voxel's `length` holds its kernel length in metres (> 0). While a scan is fused, a voxel
# the scan hit in an adaptive mode holds instead a pending mark, -(1 + its training row): the
# kernel update, which reads the voxel's counters anyway, then computes the length from the row's
# evidence in the same pass (kernels/bki.py) instead of a pass of its own.
@ti.func
def pending_length(row):
    """The mark of a voxel whose kernel length is still to be computed from training row `row`."""
    return -ti.cast(row + 1, ti.f32)


@ti.func
def is_pending(length):
    return length < 0


@ti.func
def pending_row(length):
    """The training row of a pending mark (inverse of pending_length)."""
    return ti.cast(-length, ti.i32) - 1


@ti.func
def block_and_local(w):
    """World voxel w -> (its leaf block, its index 0..63 inside the block, z slowest).

    Exact for negative indices (arithmetic shifts and two's complement masks; Taichi's integer
    floor division would add a sign fix-up per point). Sorting a block's voxels by this index
    puts each z layer of the block in one run.
    """
    local = ti.Vector([w[0] & (LEAF - 1), w[1] & (LEAF - 1), w[2] & (LEAF - 1)])
    blk = ti.Vector([w[0] >> LEAF_BITS, w[1] >> LEAF_BITS, w[2] >> LEAF_BITS])
    return blk, (local[2] * LEAF + local[1]) * LEAF + local[0]


@ti.func
def rows_below(layers, layer):
    """Training rows of a block in its z layers below `layer` (0..LEAF-1), from b_layers.
    Shifted up a byte first, so that layer 0 reads the zero byte (no branch)."""
    return ((layers << LAYER_BITS) >> (LAYER_BITS * layer)) & ((1 << LAYER_BITS) - 1)


@ti.func
def rows_to(layers, layer):
    """Training rows of a block in its z layers up to and including `layer` (0..LEAF-1)."""
    return (layers >> (LAYER_BITS * layer)) & ((1 << LAYER_BITS) - 1)


@ti.func
def local_of_index(q):
    """Inverse of the index in block_and_local: the voxel's offset inside its block."""
    return ti.Vector([q % LEAF, (q // LEAF) % LEAF, q // (LEAF * LEAF)])


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

    def __init__(
        self,
        num_classes: int,
        extent: tuple[int, int, int],
        table_half: tuple[int, int, int],
        free_space: bool = False,
        empty_evidence: float = 2.0,
        occupancy_cap: float = 4.0,
        class_centroids: bool = False,
        compact_counters: bool = False,
        seen_empty_s: float = 0.0,
        spare_beside_unseen: bool = False,
        spare_static_beside_own: bool = False,
        spare_thin_static: bool = False,
        thin_static_hold_s: float | None = None,
        thin_static_crossings: int | None = None,
    ):
        for n in extent:
            if n % TOP or n & (n - 1):
                raise ValueError(f"storage extent {extent} must be powers of two >= {TOP}")
        self.C = int(num_classes)
        self.N = tuple(int(n) for n in extent)
        self.mask = tuple(n - 1 for n in self.N)
        self.N_blk = tuple(n // LEAF for n in self.N)  # extent in leaf blocks
        self.N_top = tuple(n // TOP for n in self.N)  # extent in top cells
        # one SNode tree per map, built and finalised here
        fb = ti.FieldsBuilder()

        # map layer: 88 B per voxel of a live block (20 x f32 counters, time, length) + bitmask,
        # or with compact_counters 1.5 KB per live block and 80 B per live voxel
        self.counts = ti.field(ti.f32)
        # the voxel's last update, float32 seconds since the map's first scan
        self.t_last_rel = ti.field(ti.f32)
        # the voxel's kernel length in metres: > 0 for every live voxel, 0 elsewhere, or a
        # pending mark while a scan is fused (pending_length above)
        self.length = ti.field(ti.f32)
        self.top = fb.pointer(ti.ijk, self.N_top)
        self.blk = self.top.pointer(ti.ijk, MID)
        # the bitmask says which voxels are live: struct-fors over voxels run over t_last_rel
        self.vox = self.blk.bitmasked(ti.ijk, LEAF)
        # A block holds ~7 live voxels of 64, so counters stored for all 64 (5 KB a block) are
        # mostly zeros, and a growing map pays a page fault for each new 4 KB of them. With
        # compact_counters they sit behind a pointer per voxel, the live voxels' packed
        # together: 20 % less memory on a long drive and 40 % fewer page faults while the map
        # grows, but the update's reads through the pointer cost 3-10 % more time a scan on a
        # large live map (docs/long_drive.md). A voxel's counters are written only with its
        # time, so their pointer is live only where the voxel is (a live voxel whose evidence
        # was too small to fuse has none yet); reading those of one without gives 0, as in the
        # block.
        self.compact_counters = bool(compact_counters)
        if self.compact_counters:
            self.vox_counts = self.blk.pointer(ti.ijk, LEAF)
            self.vox_counts.dense(ti.l, self.C).place(self.counts)
        else:
            self.vox.dense(ti.l, self.C).place(self.counts)
        self.vox.place(self.t_last_rel)
        # free space (placed only when it is on, so that a map without it keeps its layout and
        # memory): the voxel's occupancy evidence, hits minus crossings by rays, decayed with
        # the counters to t_last_rel and clamped (kernels/raycast.py), and the last scan whose
        # rays or hits changed it (one change per voxel and scan, whatever the rays crossing it).
        # Both sit on the block, beside the bitmask, not under it (like `length`): taichi sets a
        # voxel's bit with an atomic OR on every write to a field under it, and a block's 64
        # evidences share 4 cache lines, read by flag_dynamic for most points (19 % faster;
        # docs/dynamic.md, Speed). They hold 0 where no voxel is live (window.py zeroes what
        # leaves).
        self.free_space = bool(free_space)
        self.empty_evidence = float(empty_evidence)  # (constants the kernels compile in)
        self.occupancy_cap = float(occupancy_cap)
        if self.free_space:
            self.occupancy = ti.field(ti.f32)
            self.free_stamp = ti.field(ti.i32)
            self.blk.dense(ti.ijk, LEAF).place(self.occupancy, self.free_stamp)
        # sub-voxel class boundaries (placed only when on, like free space): two slots of
        # (class, weight, mean offset in the voxel), 40 B per voxel (kernels/centroids.py)
        self.class_centroids = bool(class_centroids)
        if self.class_centroids:
            self.centroids = ti.field(ti.f32)
            self.vox.dense(ti.l, CENTROID_COLS).place(self.centroids)
        # the memory of space seen empty where the map holds no voxel (free space with
        # seen_empty_s > 0): per voxel, the map time until which what lands there is dynamic
        # (0: none), in a tree of its own, so that a ray through air makes no map voxel live.
        # Its blocks go once they expire (kernels/seen_empty.py): it holds at most the space
        # the rays of the last seen_empty_s seconds crossed, 256 B per leaf block.
        self.seen_empty_s = float(seen_empty_s) if self.free_space else 0.0
        if self.seen_empty_s > 0:
            self.empty_until = ti.field(ti.f32)
            self.seen_top = fb.pointer(ti.ijk, self.N_top)
            self.seen_blk = self.seen_top.pointer(ti.ijk, MID)
            self.seen_blk.dense(ti.ijk, LEAF).place(self.empty_until)
        # per class, 1 for a class that cannot move (spare_static_beside_own): its points in
        # space seen empty next to a live voxel it leads are not flagged (kernels/raycast.py)
        self.spare_static_beside_own = bool(spare_static_beside_own) and self.seen_empty_s > 0
        if self.spare_static_beside_own:
            self.static_class = ti.field(ti.i32)
            fb.dense(ti.i, self.C).place(self.static_class)
        # per class, 1 for a thin class that cannot move (spare_thin_static): rays leave a live
        # voxel it leads as it is (kernels/raycast.py)
        self.spare_thin_static = bool(spare_thin_static) and self.free_space
        if self.spare_thin_static:
            self.thin_static_class = ti.field(ti.i32)
            fb.dense(ti.i, self.C).place(self.thin_static_class)
        # (thin_static_hold_s) the spare of a voxel whose hits came and went within the hold
        # lapses once it has gone the hold without one: per voxel, beside the evidence, the
        # map time of its last hit and 1 + that of its first (0 where no scan has hit it, as
        # where no voxel is live)
        self.thin_static_hold = self.spare_thin_static and thin_static_hold_s is not None
        self.thin_static_hold_s = float(thin_static_hold_s) if self.thin_static_hold else 0.0
        # (thin_static_crossings) ... and of one the scans' rays have crossed in more than so
        # many scans since its last hit: per voxel, that count (0 where no voxel is live)
        self.thin_static_crossings = self.spare_thin_static and thin_static_crossings is not None
        self.thin_static_crossings_n = (
            int(thin_static_crossings) if self.thin_static_crossings else 0
        )
        # placed together, voxel by voxel: a ray's crossing reads them all (one cache line)
        hit_record = []
        if self.thin_static_hold:
            self.hit_time = ti.field(ti.f32)
            self.first_hit = ti.field(ti.f32)
            hit_record += [self.hit_time, self.first_hit]
        if self.thin_static_crossings:
            self.crossings_since_hit = ti.field(ti.i32)
            hit_record.append(self.crossings_since_hit)
        if hit_record:
            self.blk.dense(ti.ijk, LEAF).place(*hit_record)
        # the live voxels the scan's rays crossed (spare_beside_unseen): a crossed voxel next to
        # space no ray has seen (neither live nor in the memory) holds a surface seen from one
        # side, which the rays graze, and keeps its evidence; that is decided after every ray
        # of the scan has written the memory, so the list keeps them until then
        self.spare_beside_unseen = bool(spare_beside_unseen) and self.seen_empty_s > 0
        if self.spare_beside_unseen:
            self.crossed = ti.Vector.field(3, ti.i32)
            self.n_crossed = ti.field(ti.i32)
            fb.dense(ti.i, CROSSED_CAPACITY).place(self.crossed)
            fb.place(self.n_crossed)
        # 1 / tau per class (the per-class decay of movable classes, kernels/fusion.py)
        self.class_inv_tau = ti.field(ti.f32)
        fb.dense(ti.i, self.C).place(self.class_inv_tau)
        # a block's 64 lengths apart from the voxels' counters, in 4 cache lines instead of one
        # per voxel: the kernel update reads all 64 of every block near the scan to find its
        # live voxels (~7 of 64), and only then their counters
        self.blk.dense(ti.ijk, LEAF).place(self.length)

        # The scan's table: a dense grid of leaf blocks centred on the sensor's block, covering
        # every block a kept point can fall in plus the blocks a kernel reaches from there.
        # Per block: the scan's points (count, first slot in the block-sorted point order) and
        # its training points (first slot in the block-sorted training arrays, rows per z
        # layer). The kernel update looks the training slices up tens of times per voxel, and a
        # dense read is several times cheaper than a sparse one.
        self.table_half = tuple(int(h) for h in table_half)
        self.table_shape = tuple(2 * h + 1 for h in self.table_half)
        self.p_count = ti.field(ti.i32)
        self.p_start = ti.field(ti.i32)
        # the training rows of a block are sorted by voxel, z layer by z layer: b_layers packs
        # one byte per layer, the rows in that layer and those below it (so its last byte is the
        # block's row count), and the kernel update reads a column's z-range to the voxel layer
        self.b_start = ti.field(ti.i32)
        self.b_layers = ti.field(ti.i32)
        fb.dense(ti.ijk, self.table_shape).place(
            self.p_count, self.p_start, self.b_start, self.b_layers
        )
        # per (x, y) column of the table: the z-range of cells holding points (empty: lo > hi).
        # Each column's blocks are laid out one after another in z, so the kernel update reads
        # a column's z-range of blocks as one contiguous slice.
        self.col_lo = ti.field(ti.i32)
        self.col_hi = ti.field(ti.i32)
        fb.dense(ti.ij, self.table_shape[:2]).place(self.col_lo, self.col_hi)
        # per x row of the table: its columns' count, then its first slot (kernels/table.py
        # hands the slots out row after row, so that a scan's order never depends on threads)
        self.row_slots = ti.field(ti.i32)
        fb.dense(ti.i, self.table_shape[0]).place(self.row_slots)
        # which map blocks the scan's kernels can reach: per NEAR x NEAR x NEAR table cells, the
        # last scan with a training block within reach (kernels/lengths.py marks it). A dense
        # read per map block replaces a sparse is_active test per (training block, neighbour).
        self.near = ti.field(ti.i32)
        fb.dense(ti.ijk, tuple(2 * h // NEAR + 1 for h in self.table_half)).place(self.near)

        self.counter = ti.field(ti.i32)
        fb.place(self.counter)
        self.kernel_lut = ti.field(ti.f32)  # g(r) sampled in r^2 (kernels/bki.py)
        fb.dense(ti.i, KERNEL_TABLE + 1).place(self.kernel_lut)
        # The tree is not kept: taichi's SNodeTree object holds its Program, so a map kept past
        # a new ti.init would keep the earlier Program alive, and its late destruction (when
        # the map is collected) unmaps memory under the running runtime. Fields alone do not
        # hold the Program; the tree lives as long as its runtime, and tisem never destroys one.
        fb.finalize()
        self.col_lo.fill(EMPTY_LO)
        self.col_hi.fill(-1)

    @ti.func
    def is_empty(self, u):
        """Whether live voxel u has been seen through often enough to be empty space: its
        occupancy evidence at or below -empty_evidence (never, without free space)."""
        empty = False
        if ti.static(self.free_space):
            empty = self.occupancy[u] <= -self.empty_evidence
        return empty

    @ti.func
    def in_table(self, i):
        return (
            0 <= i[0] <= 2 * self.table_half[0]
            and 0 <= i[1] <= 2 * self.table_half[1]
            and 0 <= i[2] <= 2 * self.table_half[2]
        )

    @ti.func
    def cell_id(self, i):
        """Table cell i as one int (z fastest, like the field's own layout)."""
        return (i[0] * self.table_shape[1] + i[1]) * self.table_shape[2] + i[2]

    @ti.func
    def cell_of_id(self, f):
        """Inverse of cell_id."""
        nz = self.table_shape[2]
        nyz = self.table_shape[1] * nz
        return ti.Vector([f // nyz, (f // nz) % self.table_shape[1], f % nz])

    @ti.func
    def near_index(self, i):
        """Cell of the coarse `near` table holding training-table cell i (inside the table)."""
        return i // NEAR

    @ti.func
    def table_index(self, world_blk, center_blk):
        """(index into the table's fields, whether the block lies inside the table)."""
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
