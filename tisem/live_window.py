"""The live window: which voxels live in the Taichi field, and the host store for the rest.

The window is the voxel box |w - center_vox| <= half_vox around the sensor, the very box the
query kernel reads the field in. When it moves, kernels/window.py exports the live voxels it no
longer holds (splitting the leaf blocks its face cuts) and the store's voxels it now covers come
back, so a voxel is live exactly when the box holds it, and the field and the store never hold
the same voxel.

The window also keeps the live blocks under `max_live_blocks` (taichi 1.7.4's CPU allocator
corrupts memory once the sparse pools need a second 1 GiB chunk): when the blocks around the
sensor, live and stored, would leave less room under the cap than the most blocks one scan has
added, it shrinks in x and y, so the farthest blocks go to the store first, down to the box
that holds a scan; `free_blocks` is the room a scan then has (tisem/block_cap.py cuts a scan
that needs more).

A move either completes or, when the store cannot take what leaves (a full disk: the store's
OSError, `tisem.spill.SpillError`), raises with the field and the store as they were.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import taichi as ti

from tisem.blend import answer_blend
from tisem.geometry import MapGeometry
from tisem.kernels import centroids as kcentroids
from tisem.kernels import query as kquery
from tisem.kernels import raycast, window
from tisem.kernels.layout import CENTROID_COLS, LEAF, TOP, MapFields
from tisem.scan import finite_rows
from tisem.snapshot import MapSnapshot
from tisem.store import KEY_LIMIT, BlockStore
from tisem.voxel_arrays import VoxelArrays, from_store

log = logging.getLogger(__name__)

# query coordinates are clamped to this, so that their voxel indices fit an int32
QUERY_CLAMP_M = 1.0e6
QUERY_CLAMP_VOX = 2**30


def ivec(a) -> ti.Vector:
    """An integer array (voxel or block indices) as a Taichi kernel vector argument."""
    return ti.Vector([int(x) for x in a])


@dataclass
class WindowState:
    """What the window remembers from one scan to the next."""

    full_half_vox: np.ndarray  # the configured half-size
    half_vox: np.ndarray  # the half-size now (shrunk under the block cap)
    center_vox: np.ndarray | None = None  # local voxel of the centre; None before any scan
    headroom_blocks: int = 0  # the most blocks one scan has added so far
    blocks_after_move: int | None = None  # live blocks right after the last move
    shrunk: bool = False
    top_range: np.ndarray | None = None  # top cells the box spanned, lo then hi


@dataclass
class Evicted:
    """What one eviction moved to the store: the voxels, how many store segments hold them
    (the store's last ones), the blocks it freed, and the box's range of top cells after it."""

    voxels: VoxelArrays
    segments: int
    freed_blocks: int
    top_range: np.ndarray | None


@dataclass
class Leaving:
    """The live blocks not wholly inside the box |w - center| <= half (`blocks[:n]`, storage
    indices), and how many blocks were live."""

    center: np.ndarray
    half: np.ndarray
    blocks: np.ndarray
    n: int
    live: int


@dataclass
class WindowMove:
    """What one move of the window did."""

    evicted_voxels: int = 0
    reloaded_voxels: int = 0


class LiveWindow:
    """The live window over a map's fields and its host store."""

    def __init__(
        self, fields: MapFields, store: BlockStore, geometry: MapGeometry, max_live_blocks: int
    ):
        self._fields = fields
        self.store = store
        self._geometry = geometry
        self._cap = int(max_live_blocks)
        self._leaving_rows = np.zeros((1024, 3), np.int32)  # (`_leaving`'s buffer)
        full = geometry.window_half_vox.copy()
        self.state = WindowState(full_half_vox=full, half_vox=full.copy())

    @property
    def center_vox(self) -> np.ndarray | None:
        return self.state.center_vox

    @property
    def half_vox(self) -> np.ndarray:
        return self.state.half_vox

    @property
    def cap(self) -> int:
        """max_live_blocks: the live leaf blocks never exceed it."""
        return self._cap

    @property
    def free_blocks(self) -> int:
        """How many leaf blocks a scan may still make live here (the cap minus the blocks live
        after the last move)."""
        live = self.state.blocks_after_move
        return self._cap - (live if live is not None else self.live_blocks)

    @property
    def live_voxels(self) -> int:
        return int(kquery.count_active(self._fields.t_last_rel))

    @property
    def live_blocks(self) -> int:
        return int(kquery.count_active(self._fields.blk))

    # ------------------------------------------------------------------ moving
    def follow(self, center_vox: np.ndarray) -> WindowMove:
        """Move the window to `center_vox`: voxels that leave it go to the store, stored voxels
        it now covers come back, and the live blocks stay under the cap. Raises ValueError, with
        the map untouched, when even the smallest window that holds a scan does not fit."""
        st = self.state
        center = np.asarray(center_vox, np.int64)
        moved = st.center_vox is not None and bool(np.any(center != st.center_vox))
        # a moving window finds what leaves a box of its present size in the pass that counts
        # the live blocks (nearly always the box it keeps)
        leaving = self._leaving(center, st.half_vox) if moved else None
        live = leaving.live if leaving is not None else self.live_blocks
        if st.blocks_after_move is not None:  # (what the last scan added)
            st.headroom_blocks = max(st.headroom_blocks, live - st.blocks_after_move)
        half = self._fit_cap(center, live)
        move, left = WindowMove(), None
        if st.center_vox is not None and (moved or np.any(half != st.half_vox)):
            if leaving is None or np.any(half != leaving.half):
                leaving = self._leaving(center, half)
            left = self._evict(leaving)
            move.evicted_voxels = len(left.voxels)
        try:
            back = self.store.take_box(center, half)
        except BaseException:
            if left is not None:  # (a full disk): the window stays where it was
                self._undo_evict(left)
            raise
        st.center_vox = center
        st.half_vox = half
        if left is not None:
            st.top_range = left.top_range
        if back is not None:
            self._import(from_store(back, self._fields.C))
            move.reloaded_voxels = len(back[0])
            st.blocks_after_move = self.live_blocks
        else:
            st.blocks_after_move = live - (left.freed_blocks if left is not None else 0)
        return move

    def _leaving(self, center: np.ndarray, half: np.ndarray) -> Leaving:
        """The live blocks not wholly inside the box |w - center| <= half, blocks unwrapped
        around the present centre (kernels/window.py), in one pass that counts them all. Their
        rows go to one buffer kept between moves, grown when more blocks leave than it holds."""
        box = (ivec(np.floor_divide(self.state.center_vox, LEAF)), ivec(center), ivec(half))
        while True:
            rows = self._leaving_rows
            n, live = (int(v) for v in window.find_leaving_blocks(self._fields, *box, rows))
            if n <= len(rows):
                return Leaving(center, half.copy(), rows, n, live)
            self._leaving_rows = np.zeros((2 * n, 3), np.int32)

    def _evict(self, found: Leaving) -> Evicted:
        """Move the live voxels outside the box of `found` (its blocks) to the store and free
        the blocks and top cells they leave empty. A store that cannot take them (a full disk)
        raises with the field as it was."""
        m, st = self._fields, self.state
        center, half = found.center, found.half
        box = (ivec(center), ivec(half))
        done = Evicted(_voxel_arrays(0, m), 0, 0, st.top_range)
        blocks, n = found.blocks, found.n
        if n == 0:
            return done
        leaving = _voxel_arrays(n * LEAF**3, m)
        left = np.zeros(n, np.int32)
        occupancy = leaving.occupancy if m.free_space else np.zeros(0, np.float32)
        cent = leaving.centroids if m.class_centroids else np.zeros((0, CENTROID_COLS), np.float32)
        nv = window.export_leaving(
            m,
            ivec(st.center_vox),
            *box,
            blocks,
            n,
            leaving.keys,
            leaving.counts,
            leaving.t_last_rel,
            leaving.length_m,
            occupancy,
            cent,
            left,
        )
        done.voxels = leaving = leaving.rows(slice(0, nv))
        try:
            done.segments = self.store.put(*leaving.arrays(), box=(center, half))
        except BaseException:
            self._import(leaving)  # back where they were: the blocks are still there
            raise
        done.freed_blocks = int(window.free_empty_blocks(m, blocks, n, left))
        # a top cell can only fall wholly outside when the box's range of top cells changes
        tops = np.r_[np.floor_divide(center - half, TOP), np.floor_divide(center + half, TOP)]
        if st.top_range is None or np.any(tops != st.top_range):
            window.free_far_top_cells(m, ivec(np.floor_divide(st.center_vox, TOP)), *box)
            done.top_range = tops
        return done

    def _undo_evict(self, done: Evicted) -> None:
        """Put evicted voxels back in the field and drop them from the store again (no disk
        access: the store forgets the segments it just added)."""
        self.store.forget_last(done.segments)
        self._import(done.voxels)

    def _import(self, v: VoxelArrays) -> None:
        if len(v):
            keys = np.ascontiguousarray(v.keys, np.int32)
            kquery.import_voxels(self._fields, keys, v.counts, v.t_last_rel, v.length_m)
            if self._fields.free_space:
                occupancy = v.occupancy if v.occupancy is not None else np.zeros(len(keys))
                raycast.scatter_occupancy(
                    self._fields,
                    keys,
                    np.ascontiguousarray(occupancy, np.float32),
                    np.ascontiguousarray(v.t_last_rel, np.float32),
                )
            if self._fields.class_centroids:  # (the store keeps them for every voxel)
                cent = np.ascontiguousarray(v.centroids, np.float32)
                kcentroids.scatter_centroids(self._fields, keys, cent)

    def _fit_cap(self, center: np.ndarray, live: int) -> np.ndarray:
        """Half-size of the window for a scan at `center` under the block cap.

        The configured window, unless its blocks (live and stored) would leave less room under
        the cap than the most blocks one scan has added so far: then the largest smaller x/y box
        that does, but never one smaller than the box that holds a scan and its kernel reach.
        Raises ValueError when even that box holds more blocks than the cap.
        """
        st = self.state
        full = st.full_half_vox
        budget = self._cap - st.headroom_blocks
        center_blk = np.floor_divide(center, LEAF)
        full_blk = -(-full // LEAF)  # rings of blocks the full box can touch
        stored = self.store.count_blocks_by_ring(center_blk, full_blk)
        if live + int(stored.sum()) <= budget:
            return self._full_size(live)
        rings = np.zeros(int(full_blk[0]) + 1, np.int32)
        if st.center_vox is not None:
            window.blocks_by_ring(
                self._fields,
                ivec(np.floor_divide(st.center_vox, LEAF)),
                ivec(center_blk),
                ivec(full_blk),
                rings,
            )
        within = np.cumsum(rings + stored)  # blocks within ring r: the box of half 4r holds
        fits = np.flatnonzero(within <= budget)
        r = int(fits.max()) if len(fits) else -1
        if r >= full_blk[0]:  # (blocks now behind the full box leave with this move)
            return self._full_size(live)
        reach = self._geometry.scan_reach_vox
        r_min = -(-reach // LEAF)
        if r < r_min:
            # the smallest window that holds a scan leaves less room than scans have taken:
            # it is used all the same, as long as it fits the cap (the mapper then cuts scans
            # to the room that is left, tisem/block_cap.py)
            here = int(within[min(r_min, len(within) - 1)])
            if here > self._cap:
                res = self._geometry.resolution_m
                raise ValueError(
                    f"the live map cannot stay under max_live_blocks={self._cap}: the smallest "
                    f"window that holds a scan (+-{reach * res:.0f} m) has {here} blocks here; "
                    f"raise max_live_blocks (up to ~9 KB each) or lower max_range_m"
                )
            r = r_min
        if not st.shrunk:
            log.warning(
                "the map around the sensor needs more than max_live_blocks=%d blocks: "
                "live window shrunk to +-%.0f m (farthest blocks go to the store)",
                self._cap,
                r * LEAF * self._geometry.resolution_m,
            )
            st.shrunk = True
        half = full.copy()
        half[:2] = r * LEAF  # a box of half 4r voxels touches rings <= r
        return half

    def _full_size(self, live: int) -> np.ndarray:
        """The configured half-size, said once when a shrunk window gets it back."""
        st = self.state
        if st.shrunk:
            log.info("live window back to its full size (%d live blocks)", live)
            st.shrunk = False
        return st.full_half_vox

    # ------------------------------------------------------------------ reading
    def lookup_world(
        self,
        points_world: np.ndarray,
        origin_vox: np.ndarray,
        labels: np.ndarray,
        probs: np.ndarray | None,
        blend_radius_m: float = 0.0,
        centroid_ratio: float = 1.0,
    ) -> None:
        """`lookup` of float64 world points in a map whose local voxel 0 is `origin_vox`: far
        or non-finite points are clamped so that their voxel index fits an int32 in the kernel
        (they land outside the window either way)."""
        res = self._geometry.resolution_m
        finite = finite_rows(points_world)
        local = points_world - origin_vox * res
        if not finite.all():
            local[~finite] = 0.0
        clamp = min(QUERY_CLAMP_M, QUERY_CLAMP_VOX * res)
        self.lookup(
            np.clip(local, -clamp, clamp, out=local).astype(np.float32),
            finite,
            labels,
            probs,
            blend_radius_m,
            centroid_ratio,
        )
        if not finite.all():  # (they were looked up at the origin only to keep the index sane)
            labels[~finite] = 0
            if probs is not None:
                probs[~finite] = 0.0

    def lookup(
        self,
        local: np.ndarray,
        finite: np.ndarray,
        labels: np.ndarray,
        probs: np.ndarray | None,
        blend_radius_m: float = 0.0,
        centroid_ratio: float = 1.0,
    ) -> None:
        """Fill labels (N,) and, unless None, probs (N, C) of points at float32 local
        coordinates `local` (N, 3): from the field where the window holds their voxel, else
        from the store (`finite`: which points have a voxel at all). `blend_radius_m` > 0: a
        point in the window whose voxel holds no evidence takes the blended posterior of the
        live voxels within that radius (kernels/query.py). With class centroids, a voxel whose
        second class holds `centroid_ratio` of its leading class's evidence answers each point
        with the class whose centroid is nearer."""
        m, st = self._fields, self.state
        inv_res = 1.0 / self._geometry.resolution_m
        inside = np.zeros(len(local), np.int32)
        out_prob = probs if probs is not None else np.zeros((0, m.C), np.float32)
        kquery.query_kernel(blend_radius_m > 0)(
            m,
            local,
            ivec(st.center_vox),
            ivec(st.half_vox),
            inv_res,
            int(probs is not None),
            blend_radius_m,
            self._geometry.resolution_m,
            centroid_ratio,
            labels,
            inside,
            out_prob,
        )
        rest = finite & (inside == 0)
        seen_empty = np.zeros(len(local), bool)
        if len(self.store) and rest.any():
            # the voxel index exactly as the kernel computes it (float32 local * 1/res), so a
            # point on a voxel face finds the same voxel live or stored
            vox = np.floor(local[rest] * np.float32(inv_res)).astype(np.int64)
            snap, seen_empty[rest] = self._stored(vox, centroid_ratio)
            labels[rest] = snap.point_labels(local[rest])
            if probs is not None:
                probs[rest] = snap.probabilities()
        elif blend_radius_m > 0 and rest.any():
            # nothing stored: only the live voxels at the window's faces are within reach
            reach = np.ceil(blend_radius_m * inv_res) + 1
            vox = np.floor(local * np.float32(inv_res)).astype(np.int64)
            rest &= np.all(np.abs(vox - st.center_vox) <= st.half_vox + reach, axis=1)
        if blend_radius_m > 0:
            todo = np.flatnonzero(rest & (labels == 0) & ~seen_empty)
            self._blend_beyond(local, todo, blend_radius_m, labels, probs)

    def _blend_beyond(self, local, todo, radius_m, labels, probs) -> None:
        """The blend (tisem.blend) for points outside the window whose voxel holds no
        evidence: the kernel blends only the points in it, from the live voxels. Here every
        voxel within reach, live or stored, gives its normalised counters (a lookup of its
        centre), so that a map answers between its voxels wherever they are."""
        res = self._geometry.resolution_m

        def posterior_of(keys: np.ndarray) -> np.ndarray:
            out = np.zeros((len(keys), self._fields.C), np.float32)
            centres = ((keys + 0.5) * res).astype(np.float32)
            self.lookup(centres, np.ones(len(keys), bool), np.zeros(len(keys), np.int32), out)
            return out

        answer_blend(local, todo, res, radius_m, posterior_of, labels, probs)

    def _stored(self, vox: np.ndarray, centroid_ratio: float) -> tuple[MapSnapshot, np.ndarray]:
        """The stored voxels of local keys `vox`, a row per key: zeros where the store holds
        none (or a key beyond its range), and where the voxel is empty space (free space: it
        answers as no voxel does, as in the field); and which rows are empty space."""
        m = self._fields
        ok = np.all(np.abs(vox) <= KEY_LIMIT, axis=1)
        found, _ = self.store.lookup(vox[ok])
        columns = np.zeros((len(vox), found.shape[1]), np.float32)
        columns[ok] = found
        v = from_store((vox, columns, np.zeros(len(vox)), np.zeros(len(vox))), m.C)
        empty = np.zeros(len(vox), bool)
        if v.occupancy is not None:
            empty = v.occupancy <= -m.empty_evidence
            v.counts[empty] = 0.0
        res = self._geometry.resolution_m
        snap = MapSnapshot(vox, v.counts, v.t_last_rel, v.length_m, res, centroids=v.centroids)
        snap.centroid_ratio = centroid_ratio
        return snap, empty

    def live_arrays(self) -> VoxelArrays:
        """Every live voxel, in no particular order."""
        m = self._fields
        n = self.live_voxels
        out = _voxel_arrays(n, m)
        if n:
            got = kquery.export_voxels(
                m, ivec(self.state.center_vox), out.keys, out.counts, out.t_last_rel, out.length_m
            )
            assert got == n, f"export found {got} voxels, count found {n}"
            if m.free_space:
                raycast.gather_occupancy(m, out.keys, out.occupancy)
            if m.class_centroids:
                kcentroids.gather_centroids(m, out.keys, out.centroids)
        return out

    def stored_arrays(self) -> VoxelArrays:
        """Every stored voxel, in no particular order."""
        return from_store(self.store.arrays(), self._fields.C)


def _voxel_arrays(n: int, m: MapFields) -> VoxelArrays:
    """Room for n voxels of the map with fields `m` (with the columns it keeps)."""
    return VoxelArrays.zeros(n, m.C, m.free_space, m.class_centroids)
