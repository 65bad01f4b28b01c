"""Host-side store of blocks that left the live window (numpy, keyed by leaf block).

Voxels keep their counters, last-update times and kernel lengths while they are here; when the
sensor comes back they are written back into the Taichi field untouched, so the lazy decay then
covers the time they were away, exactly as if they had never left.

Layout. Every `put` (one scan's evictions) becomes a *segment* per face of the window the voxels
left through (a thin slab just outside it; a bigger set is cut into compact pieces of at most
SEGMENT_VOXELS): its voxels sorted by leaf block, each voxel as a 1-byte index inside its 4^3
block, the time of its last update (t_last_rel, seconds since the map's t0) and its kernel length
(length_m) as float32, and the counters compressed to their non-zero entries (a bit mask says
which classes, then a float32 per set class; a voxel holds ~5 of 20). That is ~35 B
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

from tisem.kernels.layout import LEAF
from tisem.spill import SpillError, SpillFile
from tisem.store_segments import (
    COMPACT,
    KEY_LIMIT,
    LOCAL_INDEX,
    SEGMENT_VOXELS,
    Payload,
    Segment,
    pack,
    pieces,
    ranges,
)

__all__ = ["BlockStore", "KEY_LIMIT", "SpillError", "pack"]


class BlockStore:
    """Voxels (keys relative to the map origin, times relative to its t0) grouped by block.

    A voxel is either live (in the Taichi field) or here, never both (see `put`). A block may be
    split between the two (the window's face cuts it), and its stored part may be in a few
    pieces, one per segment; `take_box` and `lookup` gather them.

    `spill_dir`: where the payload file goes (None: the system temp dir). `rewrite_floor`: the
    file is rewritten without its garbage once that is more than half of it and this many bytes.
    `segment_voxels`: the most voxels per segment (segments are read whole).
    """

    def __init__(
        self,
        num_classes: int,
        spill_dir: str | None = None,
        rewrite_floor: int = 64 << 20,
        segment_voxels: int = SEGMENT_VOXELS,
    ):
        self.C = num_classes
        self._segment_voxels = int(segment_voxels)
        self._spill = SpillFile(spill_dir, rewrite_floor)
        self._segments: list[Segment] = []
        self._voxels = 0
        self._blocks = 0
        self._box = np.zeros((0, 6), np.int64)  # (S, 6) segment bounds in blocks, lo then hi
        self._index = None  # sorted block keys -> (segment, block)

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

    @property
    def num_segments(self) -> int:
        return len(self._segments)

    @property
    def spill_file_bytes(self) -> int:
        """Bytes of the spill file in use: live payload and garbage not yet rewritten away."""
        return self._spill.file_bytes

    @property
    def spill_rewrites(self) -> int:
        """How often the spill file has been rewritten without its garbage."""
        return self._spill.rewrites

    def _overlapping(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Indices of the segments whose bounding box meets the block box [lo, hi]."""
        b = self._box
        return np.flatnonzero(np.all(b[:, :3] <= hi, axis=1) & np.all(b[:, 3:] >= lo, axis=1))

    def _read(self, s: Segment) -> Payload:
        return Payload.from_arrays(self._spill.read(s.record, s.layout(self.C)))

    def _write(self, new: list[tuple[Segment, Payload]]) -> None:
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

    def _build(self, keys, counts, t_last_rel, length_m) -> list[tuple[Segment, Payload]]:
        """Segments, not yet written, for the given voxels; a big set is cut in pieces, as a
        segment is read whole whenever a block of it is used."""
        return [
            Segment.build(keys[i], counts[i], t_last_rel[i], length_m[i])
            for i in pieces(keys, self._segment_voxels)
        ]

    def _add(self, seg: Segment) -> None:
        self._segments.append(seg)
        self._box = np.vstack([self._box, seg.bounds()[None]])
        self._voxels += seg.alive_voxels
        self._blocks += seg.alive_blocks
        self._index = None

    # ------------------------------------------------------------------ in and out
    def put(self, keys, counts, t_last_rel, length_m, box=None) -> int:
        """Store voxels; returns how many segments hold them (the store's last ones, which
        `forget_last` can take back). `box=(center, half)`: the live window they just left.
        None of them may lie inside it; as `take_box` takes every stored voxel inside the
        window each time it moves, no voxel is then ever live and stored at once. The voxels
        are stored in one segment per face of the box they left through, so each segment is a
        thin slab just outside that face and the window overlaps few segments.

        A payload that cannot be written (a full disk) raises `SpillError` (an OSError) with
        the store as it was."""
        keys = np.asarray(keys)
        if len(keys) == 0:
            return 0
        counts = np.asarray(counts, np.float32)
        if (
            keys.ndim != 2
            or keys.shape[1] != 3
            or counts.shape != (len(keys), self.C)
            or len(t_last_rel) != len(keys)
            or len(length_m) != len(keys)
        ):
            raise ValueError(
                f"put: keys (n, 3), counts (n, {self.C}), t_last_rel (n,), "
                f"length_m (n,) expected; got {keys.shape}, {counts.shape}, "
                f"{np.shape(t_last_rel)}, {np.shape(length_m)}"
            )
        if np.abs(keys).max() > KEY_LIMIT:
            raise ValueError(f"put: voxel keys beyond +-{KEY_LIMIT} of the map origin")
        voxels = (
            keys,
            counts,
            np.asarray(t_last_rel, np.float32),
            np.asarray(length_m, np.float32),
        )
        if box is None:
            new = self._build(*voxels)
        else:
            c, h = (np.asarray(v, np.int64) for v in box)
            off = keys.astype(np.int64) - c
            below, above = off < -h, off > h
            out = below | above
            if not out.any(axis=1).all():
                raise ValueError(
                    "put: voxels inside the live window cannot be stored (they "
                    "would be live and stored at once)"
                )
            axis = np.argmax(out, axis=1)  # the first axis it is outside on
            face = 2 * axis + above[np.arange(len(keys)), axis]
            new = [
                seg for f in np.unique(face) for seg in self._build(*(a[face == f] for a in voxels))
            ]
        self._write(new)
        for seg, _ in new:
            self._add(seg)
        return len(new)

    def forget_last(self, segments: int) -> None:
        """Take back the last `put` (its `segments`), which nothing has used since: the store
        is as before it, without touching the disk (the payload becomes garbage)."""
        for _ in range(segments):
            seg = self._segments.pop()
            self._spill.release(seg.record)
            self._voxels -= seg.alive_voxels
            self._blocks -= seg.alive_blocks
        if segments:
            self._box = self._box[: len(self._segments)]
            self._index = None

    @staticmethod
    def _select(s: Segment, c: np.ndarray, h: np.ndarray, read) -> tuple[np.ndarray, object]:
        """Alive blocks of s with a voxel in the box |w - c| <= h (not the stored halves of
        blocks the face cuts), and the payload if it had to be read to tell."""
        vlo, vhi = s.extent()
        meets = s.alive & np.all((vhi >= c - h) & (vlo <= c + h), axis=1)
        take = meets & np.all((vlo >= c - h) & (vhi <= c + h), axis=1)
        part = np.flatnonzero(meets & ~take)
        p = None
        if len(part):  # only blocks whose voxels lie on both sides of a face need them
            p = read(s)
            inside = np.all(np.abs(s.keys_of(p, p.voxels_of(part)) - c) <= h, axis=1)
            owner = np.repeat(np.arange(len(part)), np.diff(p.vstart)[part])
            take[part[np.bincount(owner, inside, len(part)) > 0]] = True
        return take, p

    def take_box(self, center_vox: np.ndarray, half_vox: np.ndarray):
        """Remove and return every stored voxel w with |w - center_vox| <= half_vox per axis:
        (keys int32 (n,3), counts (n,C), t_last_rel (n,), length_m (n,)), or None.

        Blocks that straddle the box's face are split: their voxels outside stay stored.
        Everything is read and every new segment written before the store changes, so an
        error (a full disk) leaves it as it was.
        """
        c = np.asarray(center_vox, np.int64)
        h = np.asarray(half_vox, np.int64)
        plans, parts = [], []  # (segment index, blocks taken, payload, voxels taken)
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
        compacted = {}  # segment index -> its compacted self, or None (all taken)
        for i, take, p, nv in plans:
            s = self._segments[i]
            if s.alive_voxels - nv < COMPACT * s.nvox:
                keep = s.alive.copy()
                keep[take] = False
                compacted[i] = s.subset(p, np.flatnonzero(keep)) if keep.any() else None
        self._write(new + [x for x in compacted.values() if x is not None])

        for i, take, _p, nv in plans:  # nothing from here on can fail
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
        """All stored voxels as (keys int32 (M,3), counts f32 (M,C), t_last_rel, length_m),
        decoded."""
        parts = []
        for s in self._segments:
            if s.alive_blocks:
                p = self._read(s)
                parts.append(s.decode(p, p.voxels_of(np.flatnonzero(s.alive)), self.C))
        if not parts:
            return (
                np.zeros((0, 3), np.int32),
                np.zeros((0, self.C), np.float32),
                np.zeros(0, np.float32),
                np.zeros(0, np.float32),
            )
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(4))

    def _block_index(self):
        if self._index is None:
            packed, seg, blk = (
                [np.zeros(0, np.int64)],
                [np.zeros(0, np.int32)],
                [np.zeros(0, np.int32)],
            )
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
        local = (keys - blocks * LEAF) @ LOCAL_INDEX
        # a block cut by the window's face can be stored in a few pieces (segments): every
        # (key, piece) pair, grouped by segment so that each segment is read once
        ask = np.repeat(np.arange(len(keys)), pieces)
        pos = ranges(first, first + pieces)
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
            table = np.full((len(ub), LEAF**3), -1, np.int64)
            vox = p.voxels_of(ub)
            table[np.repeat(np.arange(len(ub)), np.diff(p.vstart)[ub]), p.local[vox]] = vox
            v = table[row, local[mine]]
            ok = v >= 0
            counts[mine[ok]] = p.decode_counts(v[ok], self.C)
            found[mine[ok]] = True
        return counts, found
