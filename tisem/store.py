"""Host-side store of blocks that left the live window (numpy, keyed by leaf block).

Voxels keep their counters, last-update times and kernel lengths while they are here; when the
sensor comes back they are written back into the Taichi field untouched, so the lazy decay then
covers the time they were away, exactly as if they had never left.

Layout. Every `put` (one scan's evictions) becomes a *segment* per face of the window the voxels
left through (a thin slab just outside it): its voxels sorted by leaf block,
each voxel as a 1-byte index inside its 4^3 block, t_last and ell as float32, and the counters
compressed to their non-zero entries (a class byte and a float32 value each; a voxel holds ~5
of 20 classes; a bit mask says which). That is ~39 B per voxel on the synthetic loop instead of
the field's ~100 B, with no Python object per block. Blocks taken back (the sensor returned)
are marked dead and a segment is compacted once a fifth of it is dead. Each segment keeps its
bounding box in blocks, so finding what re-enters the window only looks inside the few
segments that overlap it.

Keys are voxel indices relative to the map origin; |key| <= KEY_LIMIT per axis (packed in
21 bits), which at 0.2 m is +-209 km around the first scan.
"""
from __future__ import annotations

import numpy as np

from kernels.layout import LEAF

_BITS = 21
_HALF = 1 << (_BITS - 1)
KEY_LIMIT = _HALF - 1   # |voxel index| (relative to the map origin) the packed keys can hold
_MASK = (1 << _BITS) - 1
_LOCAL = np.array([LEAF * LEAF, LEAF, 1], np.int64)   # voxel within block -> 0..LEAF^3-1
# A segment is rewritten without the blocks taken back from it (the sensor returned) once
# fewer than this fraction of its voxels are left.
COMPACT = 0.8


def pack(keys: np.ndarray) -> np.ndarray:
    """(K, 3) integer keys in [-2^20, 2^20) -> (K,) int64, order-preserving per axis."""
    k = np.asarray(keys, dtype=np.int64) + _HALF
    return (k[:, 0] << (2 * _BITS)) | (k[:, 1] << _BITS) | k[:, 2]


def unpack(packed: np.ndarray) -> np.ndarray:
    """Inverse of `pack`: (K,) int64 -> (K, 3) int64."""
    p = np.asarray(packed, dtype=np.int64)
    return np.stack([(p >> (2 * _BITS)) & _MASK, (p >> _BITS) & _MASK, p & _MASK], axis=1) - _HALF


def _ranges(starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Concatenation of arange(starts[i], stops[i]) for all i, vectorised."""
    lengths = stops - starts
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offsets = np.repeat(starts - np.cumsum(lengths) + lengths, lengths)
    return np.arange(total, dtype=np.int64) + offsets


def _mask_dtype(num_classes: int):
    return np.uint32 if num_classes <= 32 else np.uint64 if num_classes <= 64 else None


class _Segment:
    """Voxels stored together, sorted by (block, voxel in block), counters compressed: per voxel
    a bit mask of its non-zero classes and their values in class order (dense rows when there
    are more than 64 classes)."""

    __slots__ = ("packed", "bxyz", "vstart", "alive", "local", "mask", "val", "t_last", "ell",
                 "lo", "hi", "alive_blocks", "alive_voxels")

    @classmethod
    def build(cls, keys: np.ndarray, counts: np.ndarray, t_last: np.ndarray,
              ell: np.ndarray) -> "_Segment":
        keys = np.asarray(keys, np.int64)
        blocks = np.floor_divide(keys, LEAF)
        packed = pack(blocks)
        local = ((keys - blocks * LEAF) @ _LOCAL).astype(np.uint8)
        order = np.lexsort((local, packed))
        packed, blocks, local = packed[order], blocks[order], local[order]
        counts = np.asarray(counts, np.float32)[order]
        starts = np.flatnonzero(np.r_[True, packed[1:] != packed[:-1]])
        seg = cls()
        seg.packed = packed[starts]
        seg.bxyz = blocks[starts].astype(np.int32)
        seg.vstart = np.r_[starts, len(packed)].astype(np.int32)
        seg.local = local
        dtype = _mask_dtype(counts.shape[1])
        if dtype is None:
            seg.mask, seg.val = None, counts
        else:
            nz = counts != 0
            bits = (np.ones(1, dtype) << np.arange(counts.shape[1], dtype=dtype))
            seg.mask = (nz * bits).sum(axis=1, dtype=dtype)
            seg.val = counts[nz]                 # row-major: each voxel's values in class order
        seg.t_last = np.asarray(t_last, np.float32)[order]
        seg.ell = np.asarray(ell, np.float32)[order]
        seg.alive = np.ones(len(seg.packed), bool)
        seg._bounds()
        return seg

    def _bounds(self) -> None:
        self.alive_blocks = int(self.alive.sum())
        self.alive_voxels = int(np.diff(self.vstart)[self.alive].sum())
        if self.alive_blocks:
            live = self.bxyz[self.alive]
            self.lo, self.hi = live.min(axis=0), live.max(axis=0)
        else:
            self.lo = self.hi = np.zeros(3, np.int32)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.packed, self.bxyz, self.vstart, self.alive, self.local,
                                      self.val, self.t_last, self.ell)) \
            + (self.mask.nbytes if self.mask is not None else 0)

    def voxels_of(self, block_idx: np.ndarray) -> np.ndarray:
        """Indices of the voxels of the given blocks (in block order)."""
        return _ranges(self.vstart[block_idx].astype(np.int64),
                       self.vstart[block_idx + 1].astype(np.int64))

    def _entries(self, vox: np.ndarray) -> np.ndarray:
        """Indices into `val` of the given voxels' values, voxel by voxel."""
        estart = np.r_[0, np.cumsum(np.bitwise_count(self.mask), dtype=np.int64)]
        return _ranges(estart[vox], estart[vox + 1])

    def keys_of(self, vox: np.ndarray) -> np.ndarray:
        """(n, 3) int64 voxel keys of the given voxel indices."""
        block = np.searchsorted(self.vstart, vox, side="right") - 1
        local = self.local[vox].astype(np.int64)
        return self.bxyz[block].astype(np.int64) * LEAF + np.stack(
            [local // (LEAF * LEAF), (local // LEAF) % LEAF, local % LEAF], axis=1)

    def decode(self, vox: np.ndarray, num_classes: int):
        """(keys int32 (n,3), counts f32 (n,C), t_last, ell) of the given voxel indices."""
        return self.keys_of(vox).astype(np.int32), self.decode_counts(vox, num_classes), \
            self.t_last[vox], self.ell[vox]

    def decode_counts(self, vox: np.ndarray, num_classes: int) -> np.ndarray:
        if self.mask is None:
            return self.val[vox]
        bits = (self.mask[vox, None] >> np.arange(num_classes, dtype=self.mask.dtype)) & 1
        counts = np.zeros((len(vox), num_classes), np.float32)
        counts[bits.astype(bool)] = self.val[self._entries(vox)]
        return counts

    def subset(self, block_idx: np.ndarray) -> "_Segment":
        """A new segment holding only the given blocks (compaction), without decoding."""
        vox = self.voxels_of(block_idx)
        seg = _Segment()
        seg.packed = self.packed[block_idx]
        seg.bxyz = self.bxyz[block_idx]
        sizes = self.vstart[block_idx + 1] - self.vstart[block_idx]
        seg.vstart = np.r_[0, np.cumsum(sizes)].astype(np.int32)
        seg.local = self.local[vox]
        if self.mask is None:
            seg.mask, seg.val = None, self.val[vox]
        else:
            seg.mask, seg.val = self.mask[vox], self.val[self._entries(vox)]
        seg.t_last = self.t_last[vox]
        seg.ell = self.ell[vox]
        seg.alive = np.ones(len(block_idx), bool)
        seg._bounds()
        return seg


class BlockStore:
    """Voxels (keys relative to the map origin, times relative to its t0) grouped by block.

    A voxel is either live (in the Taichi field) or here, never both (see `put`). A block may be
    split between the two (the window's face cuts it), and its stored part may be in a few
    pieces, one per segment; `take_box` and `lookup` gather them.
    """

    def __init__(self, num_classes: int):
        self.C = num_classes
        self._segments: list[_Segment] = []
        self._voxels = 0
        self._blocks = 0
        self._box: np.ndarray | None = None       # (S, 6) segment bounds, lo then hi
        self._index = None                         # sorted block keys -> (segment, block)

    def __len__(self) -> int:
        return self._voxels

    @property
    def num_blocks(self) -> int:
        return self._blocks

    @property
    def nbytes(self) -> int:
        """Bytes of numpy payload held (the store's resident size, give or take)."""
        return sum(s.nbytes for s in self._segments)

    def _boxes(self) -> np.ndarray:
        if self._box is None or len(self._box) != len(self._segments):
            self._box = np.array([np.r_[s.lo, s.hi] for s in self._segments],
                                 np.int64).reshape(-1, 6)
        return self._box

    def _overlapping(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Indices of the segments whose bounding box meets the block box [lo, hi]."""
        if not self._segments:
            return np.zeros(0, np.int64)
        b = self._boxes()
        return np.flatnonzero(np.all(b[:, :3] <= hi, axis=1) & np.all(b[:, 3:] >= lo, axis=1))

    # ------------------------------------------------------------------ in and out
    def put(self, keys, counts, t_last, ell, box=None) -> None:
        """Store voxels. `box=(center, half)`: the live window they just left. None of them may
        lie inside it; as `take_box` takes every stored voxel inside the window each time it
        moves, no voxel is then ever live and stored at once. The voxels are stored in one
        segment per face of the box they left through, so each segment is a thin slab just
        outside that face and the window overlaps few segments."""
        keys = np.asarray(keys)
        if len(keys) == 0:
            return
        counts = np.asarray(counts, np.float32)
        if keys.ndim != 2 or keys.shape[1] != 3 or counts.shape != (len(keys), self.C) \
                or len(t_last) != len(keys) or len(ell) != len(keys):
            raise ValueError(f"put: keys (n, 3), counts (n, {self.C}), t_last (n,), ell (n,) "
                             f"expected; got {keys.shape}, {counts.shape}, {np.shape(t_last)}, "
                             f"{np.shape(ell)}")
        if np.abs(keys).max() > KEY_LIMIT:
            raise ValueError(f"put: voxel keys beyond +-{KEY_LIMIT} of the map origin")
        if box is None:
            self._add(_Segment.build(keys, counts, t_last, ell))
            return
        c, h = (np.asarray(v, np.int64) for v in box)
        off = keys.astype(np.int64) - c
        below, above = off < -h, off > h
        out = below | above
        if not out.any(axis=1).all():
            raise ValueError("put: voxels inside the live window cannot be stored (they would be "
                             "live and stored at once)")
        axis = np.argmax(out, axis=1)                       # the first axis it is outside on
        face = 2 * axis + above[np.arange(len(keys)), axis]
        for f in np.unique(face):
            sel = face == f
            self._add(_Segment.build(keys[sel], counts[sel], t_last[sel], ell[sel]))

    def _add(self, seg: _Segment) -> None:
        self._boxes()
        self._segments.append(seg)
        self._box = np.vstack([self._box, np.r_[seg.lo, seg.hi][None]])
        self._voxels += seg.alive_voxels
        self._blocks += seg.alive_blocks
        self._index = None

    def _take_blocks(self, lo, hi, select):
        """Remove the alive blocks `select(segment)` picks among segments overlapping [lo, hi];
        returns their voxels as (keys, counts, t_last, ell) or None."""
        parts = []
        sparse = []
        for i in self._overlapping(np.asarray(lo), np.asarray(hi)):
            s = self._segments[i]
            take = np.flatnonzero(s.alive & select(s))
            if len(take) == 0:
                continue
            parts.append(s.decode(s.voxels_of(take), self.C))
            s.alive[take] = False
            before_v, before_b = s.alive_voxels, s.alive_blocks
            s._bounds()
            self._box[i] = np.r_[s.lo, s.hi]
            self._voxels -= before_v - s.alive_voxels
            self._blocks -= before_b - s.alive_blocks
            if s.alive_voxels < COMPACT * len(s.local):   # compact (or drop)
                sparse.append(i)
        if not parts:
            return None
        for i in sparse:
            s = self._segments[i]
            self._segments[i] = s.subset(np.flatnonzero(s.alive)) if s.alive_blocks else None
        if any(self._segments[i] is None for i in sparse):
            keep = np.array([s is not None for s in self._segments])
            self._segments = [s for s in self._segments if s is not None]
            self._box = self._box[keep]
        self._index = None
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(4))

    def take_box(self, center_vox: np.ndarray, half_vox: np.ndarray):
        """Remove and return every stored voxel w with |w - center_vox| <= half_vox per axis:
        (keys int32 (n,3), counts (n,C), t_last (n,), ell (n,)), or None.

        Blocks that straddle the box's face are split: their voxels outside stay stored.
        """
        c = np.asarray(center_vox, np.int64)
        h = np.asarray(half_vox, np.int64)
        lo_blk, hi_blk = np.floor_divide(c - h, LEAF), np.floor_divide(c + h, LEAF)

        def select(s):
            """Blocks with a voxel inside (not the stored halves of blocks the face cuts)."""
            cand = np.all((s.bxyz >= lo_blk) & (s.bxyz <= hi_blk), axis=1)
            corner = s.bxyz.astype(np.int64) * LEAF
            take = cand & np.all((corner >= c - h) & (corner + LEAF - 1 <= c + h), axis=1)
            part = np.flatnonzero(cand & ~take & s.alive)
            if len(part):
                inside = np.all(np.abs(s.keys_of(s.voxels_of(part)) - c) <= h, axis=1)
                owner = np.repeat(np.arange(len(part)), np.diff(s.vstart)[part])
                take[part[np.bincount(owner, inside, len(part)) > 0]] = True
            return take

        got = self._take_blocks(lo_blk, hi_blk, select)
        if got is None:
            return None
        inside = np.all(np.abs(got[0].astype(np.int64) - c) <= h, axis=1)
        if not inside.all():      # the outside part of a cut block stays stored
            self._add(_Segment.build(*(a[~inside] for a in got)))
            got = tuple(a[inside] for a in got)
        return got

    def count_blocks_by_ring(self, center_blk: np.ndarray, half_blk: np.ndarray) -> np.ndarray:
        """Stored blocks inside the box around center_blk, by ring: entry r counts those at
        Chebyshev distance r in x/y (any z within half_blk[2]); length half_blk[0] + 1."""
        c = np.asarray(center_blk, np.int64)
        h = np.asarray(half_blk, np.int64)
        rings = np.zeros(int(h[0]) + 1, np.int64)
        for i in self._overlapping(c - h, c + h):
            s = self._segments[i]
            d = np.abs(s.bxyz[s.alive] - c)
            ring = np.maximum(d[:, 0], d[:, 1])
            ok = (ring <= h[0]) & (d[:, 2] <= h[2])
            rings += np.bincount(ring[ok], minlength=len(rings))
        return rings

    # ------------------------------------------------------------------ reading
    def arrays(self):
        """All stored voxels as (keys int32 (M,3), counts f32 (M,C), t_last, ell), decoded."""
        parts = [s.decode(s.voxels_of(np.flatnonzero(s.alive)), self.C)
                 for s in self._segments if s.alive_blocks]
        if not parts:
            return (np.zeros((0, 3), np.int32), np.zeros((0, self.C), np.float32),
                    np.zeros(0, np.float32), np.zeros(0, np.float32))
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(4))

    def _block_index(self):
        if self._index is None:
            packed, seg, blk = [], [], []
            for i, s in enumerate(self._segments):
                alive = np.flatnonzero(s.alive)
                packed.append(s.packed[alive])
                seg.append(np.full(len(alive), i, np.int32))
                blk.append(alive)
            packed = np.concatenate(packed) if packed else np.zeros(0, np.int64)
            order = np.argsort(packed)
            self._index = (packed[order], np.concatenate(seg)[order] if seg else packed,
                           np.concatenate(blk)[order] if blk else packed)
        return self._index

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Counters of the given voxels: (K, C) float32 (zeros where absent), found mask."""
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        counts = np.zeros((len(keys), self.C), np.float32)
        found = np.zeros(len(keys), bool)
        if not self._blocks or len(keys) == 0:
            return counts, found
        packed, seg_of, blk_of = self._block_index()
        blocks = np.floor_divide(keys, LEAF)
        q = pack(blocks)
        first = np.searchsorted(packed, q, side="left")
        pieces = np.searchsorted(packed, q, side="right") - first
        local = (keys - blocks * LEAF) @ _LOCAL
        # a block cut by the window's face can be stored in a few pieces (segments): try each
        for k in range(int(pieces.max())):
            ask = np.flatnonzero((pieces > k) & ~found)
            pos = first[ask] + k
            for i in np.unique(seg_of[pos]):
                s = self._segments[i]
                mine = ask[seg_of[pos] == i]
                b = blk_of[first[mine] + k]
                ub, row = np.unique(b, return_inverse=True)
                # a (blocks, LEAF^3) table of voxel indices for the blocks asked about
                table = np.full((len(ub), LEAF ** 3), -1, np.int64)
                vox = s.voxels_of(ub)
                table[np.repeat(np.arange(len(ub)), np.diff(s.vstart)[ub]), s.local[vox]] = vox
                v = table[row, local[mine]]
                ok = v >= 0
                counts[mine[ok]] = s.decode_counts(v[ok], self.C)
                found[mine[ok]] = True
        return counts, found
