"""`MapSnapshot`: the whole map as host arrays (what exports, checkpoints and the store use)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class MapSnapshot:
    """All voxels of a map, sorted by key.

    keys: (M, 3) int64 global voxel indices, voxel = floor(x_world / resolution_m).
    counts: (M, C) float32 semantic counters sigma (decayed up to t_last, not to now).
    t_last: (M,) float64 time of each voxel's last update, seconds.
    ell_m: (M,) float32 each voxel's current kernel length.
    """

    keys: np.ndarray
    counts: np.ndarray
    t_last: np.ndarray
    ell_m: np.ndarray
    resolution_m: float

    def __len__(self) -> int:
        return int(self.keys.shape[0])

    def centers(self) -> np.ndarray:
        """(M, 3) float64 voxel centres in the world frame."""
        return (self.keys.astype(np.float64) + 0.5) * self.resolution_m

    def labels(self) -> np.ndarray:
        """(M,) int32 train id per voxel: argmax of sigma, 0 where there is no evidence."""
        lab = np.argmax(self.counts, axis=1).astype(np.int32)
        lab[self.counts.sum(axis=1) <= 0] = 0
        return lab

    def probabilities(self) -> np.ndarray:
        """(M, C) normalised sigma (zeros where there is no evidence)."""
        total = self.counts.sum(axis=1, keepdims=True)
        return np.divide(self.counts, total, out=np.zeros_like(self.counts), where=total > 0)

    def confidence(self) -> np.ndarray:
        """(M,) probability of each voxel's label."""
        p = self.probabilities()
        return p[np.arange(len(self)), self.labels()]

    @staticmethod
    def sort_order(keys: np.ndarray) -> np.ndarray:
        return np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
