"""Host-side store of blocks that left the live window (numpy, keyed by leaf block).

Voxels keep their counters, last-update times and kernel lengths while they are here; when the
sensor comes back they are written back into the Taichi field untouched, so the lazy decay then
covers the time they were away, exactly as if they had never left.
"""
from __future__ import annotations

import numpy as np

from kernels.layout import LEAF

_BITS = 21
_HALF = 1 << (_BITS - 1)
KEY_LIMIT = _HALF - 1   # |voxel index| (relative to the map origin) the packed keys can hold


def pack(keys: np.ndarray) -> np.ndarray:
    """(K, 3) integer keys in [-2^20, 2^20) -> (K,) int64, order-preserving per axis."""
    k = np.asarray(keys, dtype=np.int64) + _HALF
    return (k[:, 0] << (2 * _BITS)) | (k[:, 1] << _BITS) | k[:, 2]


class BlockStore:
    """Voxels (keys relative to the map origin, times relative to its t0) grouped by block."""

    def __init__(self, num_classes: int):
        self.C = num_classes
        self._blocks: dict[int, tuple[np.ndarray, ...]] = {}
        self._voxels = 0
        self._block_keys: np.ndarray | None = None   # cache of the dict's keys as (B, 3)
        self._flat: tuple[np.ndarray, ...] | None = None  # cache for lookups

    def __len__(self) -> int:
        return self._voxels

    @property
    def num_blocks(self) -> int:
        return len(self._blocks)

    def _dirty(self) -> None:
        self._block_keys = None
        self._flat = None

    def put(self, keys, counts, t_last, ell) -> None:
        if len(keys) == 0:
            return
        blocks = np.floor_divide(keys, LEAF)
        packed = pack(blocks)
        order = np.argsort(packed, kind="stable")
        packed = packed[order]
        starts = np.flatnonzero(np.r_[True, packed[1:] != packed[:-1]])
        ends = np.r_[starts[1:], len(packed)]
        for s, e in zip(starts, ends):
            sel = order[s:e]
            key = int(packed[s])
            part = (keys[sel].astype(np.int32), counts[sel], t_last[sel], ell[sel])
            if key in self._blocks:   # a block can leave in pieces only if re-entered between
                old = self._blocks[key]
                part = tuple(np.concatenate([a, b]) for a, b in zip(old, part))
                self._voxels -= len(old[0])
            self._blocks[key] = part
            self._voxels += len(part[0])
        self._dirty()

    def _keys_array(self) -> np.ndarray:
        if self._block_keys is None:
            packed = np.fromiter(self._blocks.keys(), dtype=np.int64, count=len(self._blocks))
            mask = (1 << _BITS) - 1
            self._block_keys = np.stack([(packed >> (2 * _BITS)) & mask, (packed >> _BITS) & mask,
                                         packed & mask], axis=1) - _HALF
            self._packed = packed
        return self._block_keys

    def take_inside(self, center_blk: np.ndarray, half_blk: np.ndarray):
        """Remove and return every stored voxel whose block lies in the box around center_blk."""
        if not self._blocks:
            return None
        blocks = self._keys_array()
        inside = np.all(np.abs(blocks - center_blk) <= half_blk, axis=1)
        if not inside.any():
            return None
        parts = [self._blocks.pop(int(k)) for k in self._packed[inside]]
        out = tuple(np.concatenate([p[i] for p in parts]) for i in range(4))
        self._voxels -= len(out[0])
        self._dirty()
        return out

    def arrays(self):
        """All stored voxels as (keys int32 (M,3), counts, t_last, ell)."""
        if self._flat is None:
            if self._blocks:
                parts = list(self._blocks.values())
                self._flat = tuple(np.concatenate([p[i] for p in parts]) for i in range(4))
            else:
                self._flat = (np.zeros((0, 3), np.int32), np.zeros((0, self.C), np.float32),
                              np.zeros(0, np.float32), np.zeros(0, np.float32))
        return self._flat

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Counters of the given voxels: (K, C) float32 (zeros where absent), found mask."""
        counts = np.zeros((len(keys), self.C), np.float32)
        found = np.zeros(len(keys), bool)
        if not self._blocks or len(keys) == 0:
            return counts, found
        skeys, scounts, _, _ = self.arrays()
        spacked = pack(skeys)
        order = np.argsort(spacked)
        spacked = spacked[order]
        q = pack(keys)
        pos = np.clip(np.searchsorted(spacked, q), 0, len(spacked) - 1)
        found = spacked[pos] == q
        counts[found] = scounts[order[pos[found]]]
        return counts, found
