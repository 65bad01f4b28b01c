"""Voxels as host arrays in the map's own frame (keys relative to its origin, times to its
first scan), the form in which the live window and the store exchange them, and the
`MapSnapshot` (world keys, absolute times, sorted by key) that a map's parts make together."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tisem.class_centroids import CENTROID_COLS
from tisem.snapshot import MapSnapshot


@dataclass
class VoxelArrays:
    """Voxels as host arrays: keys relative to the map origin, times to the map's t0."""

    keys: np.ndarray  # (M, 3) int32
    counts: np.ndarray  # (M, C) float32
    t_last_rel: np.ndarray  # (M,) float32 seconds since t0
    length_m: np.ndarray  # (M,) float32 kernel length
    occupancy: np.ndarray | None = None  # (M,) float32 occupancy evidence (free space)
    centroids: np.ndarray | None = None  # (M, CENTROID_COLS) float32 class centroids

    @classmethod
    def zeros(
        cls, n: int, num_classes: int, free_space: bool, class_centroids: bool
    ) -> VoxelArrays:
        """Room for n voxels, with the columns a map of these settings keeps."""
        return cls(
            np.zeros((n, 3), np.int32),
            np.zeros((n, num_classes), np.float32),
            np.zeros(n, np.float32),
            np.zeros(n, np.float32),
            np.zeros(n, np.float32) if free_space else None,
            np.zeros((n, CENTROID_COLS), np.float32) if class_centroids else None,
        )

    def __len__(self) -> int:
        return len(self.keys)

    def arrays(self) -> tuple:
        """(keys, counts, t_last_rel, length_m) as the store takes them: with free space the
        occupancy evidence travels as one more counter column, then with class centroids their
        CENTROID_COLS columns (the store keeps any column count, and its non-zero encoding
        costs little for columns that are mostly zero)."""
        extra = [a for a in (self._occupancy_column(), self.centroids) if a is not None]
        counts = np.concatenate([self.counts, *extra], axis=1) if extra else self.counts
        return self.keys, counts, self.t_last_rel, self.length_m

    def _occupancy_column(self) -> np.ndarray | None:
        return None if self.occupancy is None else self.occupancy[:, None]

    def rows(self, keep: np.ndarray) -> VoxelArrays:
        return VoxelArrays(
            *(
                None if a is None else a[keep]
                for a in (
                    self.keys,
                    self.counts,
                    self.t_last_rel,
                    self.length_m,
                    self.occupancy,
                    self.centroids,
                )
            )
        )


def from_store(arrays: tuple, num_classes: int) -> VoxelArrays:
    """VoxelArrays of what the store gave back (`VoxelArrays.arrays` in reverse): the columns
    past the class counters are the occupancy evidence (one) and the class centroids
    (CENTROID_COLS), each when the map keeps it."""
    keys, counts, t_last_rel, length_m = arrays
    extra = counts.shape[1] - num_classes
    occupancy = centroids = None
    if extra in (1, 1 + CENTROID_COLS):
        occupancy = np.ascontiguousarray(counts[:, num_classes])
    if extra >= CENTROID_COLS:
        centroids = np.ascontiguousarray(counts[:, -CENTROID_COLS:])
    if extra:
        counts = np.ascontiguousarray(counts[:, :num_classes])
    return VoxelArrays(keys, counts, t_last_rel, length_m, occupancy, centroids)


def snapshot_of(
    parts: list[VoxelArrays],
    origin_vox: np.ndarray | None,
    t0: float | None,
    resolution_m: float,
    num_classes: int,
    empty_evidence: float | None = None,
    centroid_ratio: float | None = None,
) -> MapSnapshot:
    """The voxels of all `parts` as one snapshot, sorted by key (no parts: an empty one).
    `empty_evidence` (free space on; None: off) adds the voxels' occupancy evidence and the
    threshold at which a voxel counts as empty; `centroid_ratio` (class centroids on; None:
    off) their class centroids and the share that splits a voxel."""
    if parts:
        keys = np.concatenate([p.keys for p in parts]).astype(np.int64) + origin_vox
        order = MapSnapshot.sort_order(keys)
        snap = MapSnapshot(
            keys[order],
            np.concatenate([p.counts for p in parts])[order],
            (np.concatenate([p.t_last_rel for p in parts]).astype(np.float64) + t0)[order],
            np.concatenate([p.length_m for p in parts])[order],
            resolution_m,
        )
    else:
        order = np.zeros(0, np.int64)
        snap = MapSnapshot(
            np.zeros((0, 3), np.int64),
            np.zeros((0, num_classes), np.float32),
            np.zeros(0),
            np.zeros(0, np.float32),
            resolution_m,
        )
    if empty_evidence is not None:
        occupancy = [p.occupancy for p in parts]
        snap.occupancy = np.concatenate(occupancy)[order] if parts else np.zeros(0, np.float32)
        snap.empty_evidence = empty_evidence
    if centroid_ratio is not None:
        cent = [p.centroids for p in parts]
        snap.centroids = (
            np.concatenate(cent)[order] if parts else np.zeros((0, CENTROID_COLS), np.float32)
        )
        snap.centroid_ratio = centroid_ratio
    return snap
