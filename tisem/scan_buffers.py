"""Host buffers of one scan's steps 2-3 (the mapper's): the per-point arrays the kernels fill
and the training rows, kept across scans and grown on demand so that the hot path allocates
nothing."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from tisem.class_centroids import CENTROID_COLS


class ScanPoints(NamedTuple):
    """Per point: table cell, voxel code (kernels/rasterize.py), the points in block order and
    in voxel order; and the occupied cells (at most one per point)."""

    cell: np.ndarray
    code: np.ndarray
    by_block: np.ndarray
    by_voxel: np.ndarray
    blocks: np.ndarray


class TrainingRows(NamedTuple):
    """The scan's training points (kernels/training.py), one row per kept voxel."""

    xyz: np.ndarray  # (K, 3) centroid, local metres
    hist: np.ndarray  # (K, C) class evidence
    classes: np.ndarray  # (K,) bit c: evidence for class c
    single: np.ndarray  # (K,) the one class, or 0
    voxel: np.ndarray  # (K,) the voxel's index in its leaf block
    cent: np.ndarray  # (K, CENTROID_COLS) class centroids (written with class_centroids on)


@dataclass
class ScanBuffers:
    """Host buffers reused across scans (grown on demand) so the hot path allocates nothing."""

    per_point: np.ndarray = field(default_factory=lambda: np.zeros((5, 0), np.int32))
    rows: TrainingRows | None = None

    def points(self, n: int) -> ScanPoints:
        if self.per_point.shape[1] < n:
            cap = max(n, int(self.per_point.shape[1] * 1.5))
            self.per_point = np.zeros((5, cap), np.int32)
        # (views of exactly n, each contiguous: the kernels loop over their length)
        return ScanPoints(*(self.per_point[k, :n] for k in range(5)))

    def training(self, n: int, num_classes: int) -> TrainingRows:
        if self.rows is None or len(self.rows.xyz) < n:
            cap = max(n, int(len(self.rows.xyz) * 1.5) if self.rows is not None else n)
            self.rows = TrainingRows(
                np.zeros((cap, 3), np.float32),
                np.zeros((cap, num_classes), np.float32),
                *(np.zeros(cap, np.int32) for _ in range(3)),
                np.zeros((cap, CENTROID_COLS), np.float32),
            )
        return self.rows
