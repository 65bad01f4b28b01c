"""Host-side store of blocks that left the live window (numpy, keyed by leaf block).

Voxels keep their counters, last-update times and kernel lengths while they are here; when the
sensor comes back they are written back into the Taichi field untouched, so the lazy decay then
covers the time they were away, exactly as if they had never left.

Layout. Every `put` (one scan's evictions) becomes a *segment* per face of the window the voxels
left through (a thin slab just outside it; a bigger set is cut into compact pieces of at most
SEGMENT_VOXELS): its voxels sorted by leaf block, each voxel as a 1-byte index inside its 4^3
block, t_last and ell as float32, and the counters compressed to their non-zero entries (a bit
mask says which classes, then a float32 per set class; a voxel holds ~5 of 20). That is ~35 B
per voxel (8-16 voxels per block) instead of the field's ~100 B, with no Python object per
block.
Blocks taken back (the sensor returned) are marked dead and a segment is compacted once a fifth
of it is dead.

On disk and in memory. The per-voxel payload (~97% of the bytes) lives in one unnamed temporary
file (tisem/spill.py), so resident memory stays flat however long the drive; a segment's payload
is read back whole when one of its blocks is taken, looked up or exported. In memory each
segment keeps only what the window asks before every scan, so that a scan that takes nothing
reads nothing: its blocks' coordinates (int16 offsets, for `count_blocks_by_ring` and for
finding what the window covers), each block's voxel extent (2 B, which tells for all but a few
blocks that the face cuts whether the window holds any of its voxels) and which blocks are still
here: ~9 B per block, 0.6-1.1 B per voxel (measured: tests/test_window.py). The store keeps
every segment's bounding box, so it only looks inside the few segments that overlap the window.

Keys are voxel indices relative to the map origin; |key| <= KEY_LIMIT per axis (packed in
21 bits), which at 0.2 m is +-209 km around the first scan.
"""
from __future__ import annotations

import numpy as np

from kernels.layout import LEAF
from tisem.spill import SpillFile

_BITS = 21
_HALF = 1 << (_BITS - 1)
KEY_LIMIT = _HALF - 1   # |voxel index| (relative to the map origin) the packed keys can hold
_MASK = (1 << _BITS) - 1
_LOCAL = np.array([LEAF * LEAF, LEAF, 1], np.int64)   # voxel within block -> 0..LEAF^3-1
# A segment is rewritten without the blocks taken back from it (the sensor returned) once
# fewer than this fraction of its voxels are left.
COMPACT = 0.8
# Segments are read whole: a bigger set of voxels (a restored map, a window emptied by a jump)
# is cut into pieces of at most this many (~2.5 MB) so that using one block reads little.
SEGMENT_VOXELS = 1 << 16


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


# A block's voxel extent: lowest and highest voxel per axis inside the block, 2 bits each.
_EB = (LEAF - 1).bit_length()
assert 6 * _EB <= 16, "the voxel extent of a block must fit a uint16"
_SHIFTS = np.arange(6, dtype=np.uint16) * _EB


def _pieces(keys: np.ndarray) -> list[np.ndarray]:
    """Index sets that split voxels into pieces of at most SEGMENT_VOXELS, cut between blocks at
    the median x or y (a k-d split), so that each piece stays compact in space."""
    blocks = np.floor_divide(keys[:, :2], LEAF)
    out, todo = [], [np.arange(len(keys))]
    while todo:
        idx = todo.pop()
        if len(idx) <= SEGMENT_VOXELS:
            out.append(idx)
            continue
        b = blocks[idx]
        col = b[:, int(np.argmax(b.max(axis=0) - b.min(axis=0)))]
        cut = np.partition(col, len(col) // 2)[len(col) // 2]
        left = col < cut if (col < cut).any() else col <= cut
        if left.all():      # a single column of blocks: no cut between blocks
            out.append(idx)
            continue
        todo += [idx[left], idx[~left]]
    return out


class _Payload:
    """A segment's voxel arrays, as in the spill file: voxels sorted by (block, voxel in block);
    `vstart` (B+1) the first voxel of each block; per voxel the index in its block (`local`),
    a bit mask of its non-zero classes and their values in class order in `val` (`mask` None
    and dense (V, C) rows in `val` when there are more than 64 classes), t_last, ell."""

    __slots__ = ("vstart", "local", "mask", "val", "t_last", "ell")

    def __init__(self, vstart, local, mask, val, t_last, ell):
        self.vstart, self.local, self.mask, self.val = vstart, local, mask, val
        self.t_last, self.ell = t_last, ell

    def arrays(self) -> list[np.ndarray]:
        mid = [self.val] if self.mask is None else [self.mask, self.val]
        return [self.vstart, self.local] + mid + [self.t_last, self.ell]

    @classmethod
    def from_arrays(cls, arrays: list[np.ndarray]) -> "_Payload":
        vstart, local, *mid, t_last, ell = arrays
        mask, val = mid if len(mid) == 2 else (None, mid[0])
        return cls(vstart, local, mask, val, t_last, ell)

    def voxels_of(self, block_idx: np.ndarray) -> np.ndarray:
        """Indices of the voxels of the given blocks (in block order)."""
        return _ranges(self.vstart[block_idx].astype(np.int64),
                       self.vstart[np.asarray(block_idx) + 1].astype(np.int64))

    def entries(self, vox: np.ndarray) -> np.ndarray:
        """Indices into `val` of the given voxels' values, voxel by voxel."""
        estart = np.r_[0, np.cumsum(np.bitwise_count(self.mask), dtype=np.int64)]
        return _ranges(estart[vox], estart[vox + 1])

    def decode_counts(self, vox: np.ndarray, num_classes: int) -> np.ndarray:
        if self.mask is None:
            return self.val[vox]
        bits = (self.mask[vox, None] >> np.arange(num_classes, dtype=self.mask.dtype)) & 1
        counts = np.zeros((len(vox), num_classes), np.float32)
        counts[bits.astype(bool)] = self.val[self.entries(vox)]
        return counts

    def subset(self, block_idx: np.ndarray) -> "_Payload":
        """Only the given blocks, without decoding."""
        vox = self.voxels_of(block_idx)
        sizes = np.diff(self.vstart)[block_idx]
        if self.mask is None:
            mask, val = None, self.val[vox]
        else:
            mask, val = self.mask[vox], self.val[self.entries(vox)]
        return _Payload(np.r_[0, np.cumsum(sizes)].astype(np.int32), self.local[vox], mask, val,
                        self.t_last[vox], self.ell[vox])


class _Segment:
    """What stays in memory of a segment: its blocks (as int16 offsets from `base` where they
    fit), each block's voxel extent, which blocks are still here, and where its `_Payload` lies
    in the spill file."""

    __slots__ = ("base", "rel", "ext", "alive", "nvox", "nent", "record", "alive_blocks",
                 "alive_voxels")

    def __init__(self, blocks: np.ndarray, ext: np.ndarray, payload: _Payload):
        self.base = blocks.min(axis=0)
        rel = blocks - self.base
        self.rel = rel.astype(np.int16 if rel.max() < 1 << 15 else np.int32)
        self.ext = ext
        self.alive = np.ones(len(blocks), bool)
        self.nvox, self.nent = len(payload.local), len(payload.val)
        self.record = None                     # set once the payload is written
        self.alive_blocks, self.alive_voxels = len(blocks), self.nvox

    @classmethod
    def build(cls, keys: np.ndarray, counts: np.ndarray, t_last: np.ndarray,
              ell: np.ndarray) -> tuple["_Segment", _Payload]:
        keys = np.asarray(keys, np.int64)
        blocks = np.floor_divide(keys, LEAF)
        packed = pack(blocks)
        inner = keys - blocks * LEAF
        local = inner @ _LOCAL
        order = np.lexsort((local, packed))
        packed, blocks, inner, local = packed[order], blocks[order], inner[order], local[order]
        counts = np.asarray(counts, np.float32)[order]
        starts = np.flatnonzero(np.r_[True, packed[1:] != packed[:-1]])
        lo, hi = np.minimum.reduceat(inner, starts), np.maximum.reduceat(inner, starts)
        ext = (np.concatenate([lo, hi], axis=1).astype(np.uint16) << _SHIFTS).sum(
            axis=1, dtype=np.uint16)
        dtype = _mask_dtype(counts.shape[1])
        if dtype is None:
            mask, val = None, counts
        else:
            nz = counts != 0
            bits = (np.ones(1, dtype) << np.arange(counts.shape[1], dtype=dtype))
            mask = (nz * bits).sum(axis=1, dtype=dtype)
            val = counts[nz]                     # row-major: each voxel's values in class order
        p = _Payload(np.r_[starts, len(packed)].astype(np.int32),
                     local.astype(np.uint8), mask, val,
                     np.asarray(t_last, np.float32)[order], np.asarray(ell, np.float32)[order])
        return cls(blocks[starts], ext, p), p

    def subset(self, p: _Payload, block_idx: np.ndarray) -> tuple["_Segment", _Payload]:
        """A new segment holding only the given blocks (compaction), without decoding."""
        q = p.subset(block_idx)
        return _Segment(self.blocks(block_idx), self.ext[block_idx], q), q

    def layout(self, num_classes: int) -> list:
        """[(dtype, shape)] of `_Payload.arrays()`, to read the record back."""
        v = (self.nvox,)
        dtype = _mask_dtype(num_classes)
        mid = [(np.float32, (self.nvox, num_classes))] if dtype is None else \
            [(dtype, v), (np.float32, (self.nent,))]
        return [(np.int32, (len(self.alive) + 1,)), (np.uint8, v)] + mid + [(np.float32, v)] * 2

    @property
    def nbytes(self) -> int:
        return self.rel.nbytes + self.ext.nbytes + self.alive.nbytes + self.base.nbytes

    def blocks(self, idx=slice(None)) -> np.ndarray:
        """(n, 3) int64 block coordinates of the given blocks."""
        return self.rel[idx].astype(np.int64) + self.base

    def extent(self, idx=slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) lowest and highest voxel keys of the given blocks."""
        f = (self.ext[idx, None] >> _SHIFTS) & (LEAF - 1)
        corner = self.blocks(idx) * LEAF
        return corner + f[:, :3], corner + f[:, 3:]

    def bounds(self) -> np.ndarray:
        """lo then hi of the alive blocks' coordinates (zeros when none is left)."""
        if not self.alive_blocks:
            return np.zeros(6, np.int64)
        live = self.blocks(self.alive)
        return np.r_[live.min(axis=0), live.max(axis=0)]

    def keys_of(self, p: _Payload, vox: np.ndarray) -> np.ndarray:
        """(n, 3) int64 voxel keys of the given voxel indices."""
        block = np.searchsorted(p.vstart, vox, side="right") - 1
        local = p.local[vox].astype(np.int64)
        return self.blocks(block) * LEAF + np.stack(
            [local // (LEAF * LEAF), (local // LEAF) % LEAF, local % LEAF], axis=1)

    def decode(self, p: _Payload, vox: np.ndarray, num_classes: int):
        """(keys int32 (n,3), counts f32 (n,C), t_last, ell) of the given voxel indices."""
        return self.keys_of(p, vox).astype(np.int32), p.decode_counts(vox, num_classes), \
            p.t_last[vox], p.ell[vox]


class BlockStore:
    """Voxels (keys relative to the map origin, times relative to its t0) grouped by block.

    A voxel is either live (in the Taichi field) or here, never both (see `put`). A block may be
    split between the two (the window's face cuts it), and its stored part may be in a few
    pieces, one per segment; `take_box` and `lookup` gather them.

    `spill_dir`: where the payload file goes (None: the system temp dir). `rewrite_floor`: the
    file is rewritten without its garbage once that is more than half of it and this many bytes.
    """

    def __init__(self, num_classes: int, spill_dir: str | None = None,
                 rewrite_floor: int = 64 << 20):
        self.C = num_classes
        self._spill = SpillFile(spill_dir, rewrite_floor)
        self._segments: list[_Segment] = []
        self._voxels = 0
        self._blocks = 0
        self._box = np.zeros((0, 6), np.int64)    # (S, 6) segment bounds in blocks, lo then hi
        self._index = None                         # sorted block keys -> (segment, block)

    def __len__(self) -> int:
        return self._voxels

    @property
    def num_blocks(self) -> int:
        return self._blocks

    @property
    def nbytes(self) -> int:
        """Bytes of numpy arrays held in memory (the payload is on disk: `disk_bytes`)."""
        index = sum(a.nbytes for a in self._index) if self._index is not None else 0
        return sum(s.nbytes for s in self._segments) + self._box.nbytes + index

    @property
    def disk_bytes(self) -> int:
        """Bytes of payload in the spill file (live records; the file may hold some garbage)."""
        return self._spill.live_bytes

    def _overlapping(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Indices of the segments whose bounding box meets the block box [lo, hi]."""
        b = self._box
        return np.flatnonzero(np.all(b[:, :3] <= hi, axis=1) & np.all(b[:, 3:] >= lo, axis=1))

    def _read(self, s: _Segment) -> _Payload:
        return _Payload.from_arrays(self._spill.read(s.record, s.layout(self.C)))

    def _write(self, new: list[tuple[_Segment, _Payload]]) -> None:
        """Write the payloads of new segments: all of them, or none (then raise)."""
        done = []
        try:
            for seg, p in new:
                seg.record = self._spill.append(p.arrays())
                done.append(seg)
        except BaseException:
            for seg in done:
                self._spill.release(seg.record)
            raise

    def _build(self, keys, counts, t_last, ell) -> list[tuple[_Segment, _Payload]]:
        """Segments, not yet written, for the given voxels; a big set is cut in pieces, as a
        segment is read whole whenever a block of it is used."""
        return [_Segment.build(keys[i], counts[i], t_last[i], ell[i]) for i in _pieces(keys)]

    def _add(self, seg: _Segment) -> None:
        self._segments.append(seg)
        self._box = np.vstack([self._box, seg.bounds()[None]])
        self._voxels += seg.alive_voxels
        self._blocks += seg.alive_blocks
        self._index = None

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
        voxels = (keys, counts, np.asarray(t_last, np.float32), np.asarray(ell, np.float32))
        if box is None:
            new = self._build(*voxels)
        else:
            c, h = (np.asarray(v, np.int64) for v in box)
            off = keys.astype(np.int64) - c
            below, above = off < -h, off > h
            out = below | above
            if not out.any(axis=1).all():
                raise ValueError("put: voxels inside the live window cannot be stored (they "
                                 "would be live and stored at once)")
            axis = np.argmax(out, axis=1)                       # the first axis it is outside on
            face = 2 * axis + above[np.arange(len(keys)), axis]
            new = [seg for f in np.unique(face)
                   for seg in self._build(*(a[face == f] for a in voxels))]
        self._write(new)
        for seg, _ in new:
            self._add(seg)

    @staticmethod
    def _select(s: _Segment, c: np.ndarray, h: np.ndarray, read) -> tuple[np.ndarray, object]:
        """Alive blocks of s with a voxel in the box |w - c| <= h (not the stored halves of
        blocks the face cuts), and the payload if it had to be read to tell."""
        vlo, vhi = s.extent()
        meets = s.alive & np.all((vhi >= c - h) & (vlo <= c + h), axis=1)
        take = meets & np.all((vlo >= c - h) & (vhi <= c + h), axis=1)
        part = np.flatnonzero(meets & ~take)
        p = None
        if len(part):     # only blocks whose voxels lie on both sides of a face need them
            p = read(s)
            inside = np.all(np.abs(s.keys_of(p, p.voxels_of(part)) - c) <= h, axis=1)
            owner = np.repeat(np.arange(len(part)), np.diff(p.vstart)[part])
            take[part[np.bincount(owner, inside, len(part)) > 0]] = True
        return take, p

    def take_box(self, center_vox: np.ndarray, half_vox: np.ndarray):
        """Remove and return every stored voxel w with |w - center_vox| <= half_vox per axis:
        (keys int32 (n,3), counts (n,C), t_last (n,), ell (n,)), or None.

        Blocks that straddle the box's face are split: their voxels outside stay stored.
        Everything is read and every new segment written before the store changes, so an
        error (a full disk) leaves it as it was.
        """
        c = np.asarray(center_vox, np.int64)
        h = np.asarray(half_vox, np.int64)
        plans, parts = [], []       # (segment index, blocks taken, payload, voxels taken)
        for i in self._overlapping(np.floor_divide(c - h, LEAF), np.floor_divide(c + h, LEAF)):
            s = self._segments[i]
            take, p = self._select(s, c, h, self._read)
            take = np.flatnonzero(take)
            if len(take) == 0:
                continue
            p = p if p is not None else self._read(s)
            vox = p.voxels_of(take)
            parts.append(s.decode(p, vox, self.C))
            plans.append((i, take, p, len(vox)))
        if not parts:
            return None
        got = tuple(np.concatenate([p[k] for p in parts]) for k in range(4))
        inside = np.all(np.abs(got[0].astype(np.int64) - c) <= h, axis=1)
        # the outside part of a cut block stays stored
        new = self._build(*(a[~inside] for a in got)) if not inside.all() else []
        compacted = {}              # segment index -> its compacted self, or None (all taken)
        for i, take, p, nv in plans:
            s = self._segments[i]
            if s.alive_voxels - nv < COMPACT * s.nvox:
                keep = s.alive.copy()
                keep[take] = False
                compacted[i] = s.subset(p, np.flatnonzero(keep)) if keep.any() else None
        self._write(new + [x for x in compacted.values() if x is not None])

        for i, take, p, nv in plans:      # nothing from here on can fail
            s = self._segments[i]
            self._voxels -= nv
            self._blocks -= len(take)
            if i in compacted:
                self._spill.release(s.record)
                s = self._segments[i] = compacted[i][0] if compacted[i] else None
            else:
                s.alive[take] = False
                s.alive_blocks -= len(take)
                s.alive_voxels -= nv
            if s is not None:
                self._box[i] = s.bounds()
        if any(v is None for v in compacted.values()):
            keep = np.array([s is not None for s in self._segments])
            self._segments = [s for s in self._segments if s is not None]
            self._box = self._box[keep]
        for seg, _ in new:
            self._add(seg)
        self._index = None
        return tuple(a[inside] for a in got) if not inside.all() else got

    def count_blocks_by_ring(self, center_blk: np.ndarray, half_blk: np.ndarray) -> np.ndarray:
        """Stored blocks inside the box around center_blk, by ring: entry r counts those at
        Chebyshev distance r in x/y (any z within half_blk[2]); length half_blk[0] + 1.
        Called before every scan: it uses only what is in memory."""
        c = np.asarray(center_blk, np.int64)
        h = np.asarray(half_blk, np.int64)
        rings = np.zeros(int(h[0]) + 1, np.int64)
        for i in self._overlapping(c - h, c + h):
            s = self._segments[i]
            d = np.abs(s.blocks(s.alive) - c)
            ring = np.maximum(d[:, 0], d[:, 1])
            ok = (ring <= h[0]) & (d[:, 2] <= h[2])
            rings += np.bincount(ring[ok], minlength=len(rings))
        return rings

    # ------------------------------------------------------------------ reading
    def arrays(self):
        """All stored voxels as (keys int32 (M,3), counts f32 (M,C), t_last, ell), decoded."""
        parts = []
        for s in self._segments:
            if s.alive_blocks:
                p = self._read(s)
                parts.append(s.decode(p, p.voxels_of(np.flatnonzero(s.alive)), self.C))
        if not parts:
            return (np.zeros((0, 3), np.int32), np.zeros((0, self.C), np.float32),
                    np.zeros(0, np.float32), np.zeros(0, np.float32))
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(4))

    def _block_index(self):
        if self._index is None:
            packed, seg, blk = [np.zeros(0, np.int64)], [np.zeros(0, np.int32)], \
                [np.zeros(0, np.int32)]
            for i, s in enumerate(self._segments):
                alive = np.flatnonzero(s.alive)
                packed.append(pack(s.blocks(alive)))
                seg.append(np.full(len(alive), i, np.int32))
                blk.append(alive.astype(np.int32))
            packed = np.concatenate(packed)
            order = np.argsort(packed)
            self._index = (packed[order], np.concatenate(seg)[order], np.concatenate(blk)[order])
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
        # a block cut by the window's face can be stored in a few pieces (segments): every
        # (key, piece) pair, grouped by segment so that each segment is read once
        ask = np.repeat(np.arange(len(keys)), pieces)
        pos = _ranges(first, first + pieces)
        order = np.argsort(seg_of[pos], kind="stable")
        ask, pos = ask[order], pos[order]
        seg = seg_of[pos]
        cuts = np.flatnonzero(np.r_[True, seg[1:] != seg[:-1]]) if len(seg) else seg
        for a, b in zip(cuts, np.r_[cuts[1:], len(seg)]):
            s = self._segments[seg[a]]
            p = self._read(s)
            mine = ask[a:b]
            ub, row = np.unique(blk_of[pos[a:b]], return_inverse=True)
            # a (blocks, LEAF^3) table of voxel indices for the blocks asked about
            table = np.full((len(ub), LEAF ** 3), -1, np.int64)
            vox = p.voxels_of(ub)
            table[np.repeat(np.arange(len(ub)), np.diff(p.vstart)[ub]), p.local[vox]] = vox
            v = table[row, local[mine]]
            ok = v >= 0
            counts[mine[ok]] = p.decode_counts(v[ok], self.C)
            found[mine[ok]] = True
        return counts, found
