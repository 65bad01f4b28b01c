"""The pieces of the host store (tisem/store.py): packed keys, and segments of voxels.

A *segment* holds the voxels of one `BlockStore.put` (or a compact piece of a big one): in
memory only what the live window asks before every scan (its blocks' coordinates as int16
offsets, each block's voxel extent, which blocks are still stored), and on disk, in the spill
file, its `Payload`: the voxels sorted by leaf block, each as a 1-byte index inside its 4^3
block, t_last_rel and length_m as float32, and the counters compressed to their non-zero entries
(a bit mask says which classes, then a float32 per set class; a voxel holds ~5 of 20).
"""

from __future__ import annotations

import numpy as np

from tisem.kernels.layout import LEAF

_BITS = 21
_HALF = 1 << (_BITS - 1)
KEY_LIMIT = _HALF - 1  # |voxel index| (relative to the map origin) the packed keys can hold
_MASK = (1 << _BITS) - 1
LOCAL_INDEX = np.array([LEAF * LEAF, LEAF, 1], np.int64)  # voxel within block -> 0..LEAF^3-1
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


def ranges(starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
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


def pieces(keys: np.ndarray, max_voxels: int = SEGMENT_VOXELS) -> list[np.ndarray]:
    """Index sets that split voxels into pieces of at most `max_voxels`, cut between blocks at
    the median x or y (a k-d split), so that each piece stays compact in space."""
    blocks = np.floor_divide(keys[:, :2], LEAF)
    out, todo = [], [np.arange(len(keys))]
    while todo:
        idx = todo.pop()
        if len(idx) <= max_voxels:
            out.append(idx)
            continue
        b = blocks[idx]
        col = b[:, int(np.argmax(b.max(axis=0) - b.min(axis=0)))]
        cut = np.partition(col, len(col) // 2)[len(col) // 2]
        left = col < cut if (col < cut).any() else col <= cut
        if left.all():  # a single column of blocks: no cut between blocks
            out.append(idx)
            continue
        todo += [idx[left], idx[~left]]
    return out


class Payload:
    """A segment's voxel arrays, as in the spill file: voxels sorted by (block, voxel in block);
    `vstart` (B+1) the first voxel of each block; per voxel the index in its block (`local`),
    a bit mask of its non-zero classes and their values in class order in `val` (`mask` None
    and dense (V, C) rows in `val` when there are more than 64 classes), t_last_rel, length_m."""

    __slots__ = ("vstart", "local", "mask", "val", "t_last_rel", "length_m")

    def __init__(self, vstart, local, mask, val, t_last_rel, length_m):
        self.vstart, self.local, self.mask, self.val = vstart, local, mask, val
        self.t_last_rel, self.length_m = t_last_rel, length_m

    def arrays(self) -> list[np.ndarray]:
        mid = [self.val] if self.mask is None else [self.mask, self.val]
        return [self.vstart, self.local] + mid + [self.t_last_rel, self.length_m]

    @classmethod
    def from_arrays(cls, arrays: list[np.ndarray]) -> Payload:
        vstart, local, *mid, t_last_rel, length_m = arrays
        mask, val = mid if len(mid) == 2 else (None, mid[0])
        return cls(vstart, local, mask, val, t_last_rel, length_m)

    def voxels_of(self, block_idx: np.ndarray) -> np.ndarray:
        """Indices of the voxels of the given blocks (in block order)."""
        return ranges(
            self.vstart[block_idx].astype(np.int64),
            self.vstart[np.asarray(block_idx) + 1].astype(np.int64),
        )

    def entries(self, vox: np.ndarray) -> np.ndarray:
        """Indices into `val` of the given voxels' values, voxel by voxel."""
        estart = np.r_[0, np.cumsum(np.bitwise_count(self.mask), dtype=np.int64)]
        return ranges(estart[vox], estart[vox + 1])

    def decode_counts(self, vox: np.ndarray, num_classes: int) -> np.ndarray:
        if self.mask is None:
            return self.val[vox]
        bits = (self.mask[vox, None] >> np.arange(num_classes, dtype=self.mask.dtype)) & 1
        counts = np.zeros((len(vox), num_classes), np.float32)
        counts[bits.astype(bool)] = self.val[self.entries(vox)]
        return counts

    def subset(self, block_idx: np.ndarray) -> Payload:
        """Only the given blocks, without decoding."""
        vox = self.voxels_of(block_idx)
        sizes = np.diff(self.vstart)[block_idx]
        if self.mask is None:
            mask, val = None, self.val[vox]
        else:
            mask, val = self.mask[vox], self.val[self.entries(vox)]
        return Payload(
            np.r_[0, np.cumsum(sizes)].astype(np.int32),
            self.local[vox],
            mask,
            val,
            self.t_last_rel[vox],
            self.length_m[vox],
        )


class Segment:
    """What stays in memory of a segment: its blocks (as int16 offsets from `base` where they
    fit), each block's voxel extent, which blocks are still here, and where its `Payload` lies
    in the spill file."""

    __slots__ = (
        "base",
        "rel",
        "ext",
        "alive",
        "nvox",
        "nent",
        "record",
        "alive_blocks",
        "alive_voxels",
    )

    def __init__(self, blocks: np.ndarray, ext: np.ndarray, payload: Payload):
        self.base = blocks.min(axis=0)
        rel = blocks - self.base
        self.rel = rel.astype(np.int16 if rel.max() < 1 << 15 else np.int32)
        self.ext = ext
        self.alive = np.ones(len(blocks), bool)
        self.nvox, self.nent = len(payload.local), len(payload.val)
        self.record = None  # set once the payload is written
        self.alive_blocks, self.alive_voxels = len(blocks), self.nvox

    @classmethod
    def build(
        cls, keys: np.ndarray, counts: np.ndarray, t_last_rel: np.ndarray, length_m: np.ndarray
    ) -> tuple[Segment, Payload]:
        keys = np.asarray(keys, np.int64)
        blocks = np.floor_divide(keys, LEAF)
        packed = pack(blocks)
        inner = keys - blocks * LEAF
        local = inner @ LOCAL_INDEX
        order = np.lexsort((local, packed))
        packed, blocks, inner, local = packed[order], blocks[order], inner[order], local[order]
        counts = np.asarray(counts, np.float32)[order]
        starts = np.flatnonzero(np.r_[True, packed[1:] != packed[:-1]])
        lo, hi = np.minimum.reduceat(inner, starts), np.maximum.reduceat(inner, starts)
        ext = (np.concatenate([lo, hi], axis=1).astype(np.uint16) << _SHIFTS).sum(
            axis=1, dtype=np.uint16
        )
        dtype = _mask_dtype(counts.shape[1])
        if dtype is None:
            mask, val = None, counts
        else:
            nz = counts != 0
            bits = np.ones(1, dtype) << np.arange(counts.shape[1], dtype=dtype)
            mask = (nz * bits).sum(axis=1, dtype=dtype)
            val = counts[nz]  # row-major: each voxel's values in class order
        p = Payload(
            np.r_[starts, len(packed)].astype(np.int32),
            local.astype(np.uint8),
            mask,
            val,
            np.asarray(t_last_rel, np.float32)[order],
            np.asarray(length_m, np.float32)[order],
        )
        return cls(blocks[starts], ext, p), p

    def subset(self, p: Payload, block_idx: np.ndarray) -> tuple[Segment, Payload]:
        """A new segment holding only the given blocks (compaction), without decoding."""
        q = p.subset(block_idx)
        return Segment(self.blocks(block_idx), self.ext[block_idx], q), q

    def layout(self, num_classes: int) -> list:
        """[(dtype, shape)] of `Payload.arrays()`, to read the record back."""
        v = (self.nvox,)
        dtype = _mask_dtype(num_classes)
        mid = (
            [(np.float32, (self.nvox, num_classes))]
            if dtype is None
            else [(dtype, v), (np.float32, (self.nent,))]
        )
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

    def keys_of(self, p: Payload, vox: np.ndarray) -> np.ndarray:
        """(n, 3) int64 voxel keys of the given voxel indices."""
        block = np.searchsorted(p.vstart, vox, side="right") - 1
        local = p.local[vox].astype(np.int64)
        return self.blocks(block) * LEAF + np.stack(
            [local // (LEAF * LEAF), (local // LEAF) % LEAF, local % LEAF], axis=1
        )

    def decode(self, p: Payload, vox: np.ndarray, num_classes: int):
        """(keys int32 (n,3), counts f32 (n,C), t_last_rel, length_m) of the given voxel indices."""
        return (
            self.keys_of(p, vox).astype(np.int32),
            p.decode_counts(vox, num_classes),
            p.t_last_rel[vox],
            p.length_m[vox],
        )
