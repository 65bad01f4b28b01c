"""`MapSnapshot`: the whole map as host arrays (what exports, checkpoints and the store use)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tisem.class_centroids import split_labels


@dataclass
class MapSnapshot:
    """All voxels of a map, sorted by key.

    keys: (M, 3) int64 global voxel indices, voxel = floor(x_world / resolution_m).
    counts: (M, C) float32 semantic counters sigma (decayed up to t_last, not to now).
    t_last: (M,) float64 time of each voxel's last update, seconds.
    ell_m: (M,) float32 each voxel's current kernel length.
    occupancy: (M,) float32 occupancy evidence (hits minus crossings by rays, decayed like
        sigma), only in a map with free space; a voxel at or below -empty_evidence is empty
        space: no label, no probabilities, and not in the static map.
    centroids: (M, CENTROID_COLS) float32 class centroids (tisem/class_centroids.py), only in a
        map that keeps them; a point in a voxel whose second class holds at least
        `centroid_ratio` of the leading class's evidence takes the nearer class
        (`point_labels`). A voxel's own label stays its argmax.
    """

    keys: np.ndarray
    counts: np.ndarray
    t_last: np.ndarray
    ell_m: np.ndarray
    resolution_m: float
    occupancy: np.ndarray | None = None
    empty_evidence: float = float("inf")
    centroids: np.ndarray | None = None
    centroid_ratio: float = 1.0

    def __len__(self) -> int:
        return int(self.keys.shape[0])

    def centers(self) -> np.ndarray:
        """(M, 3) float64 voxel centres in the world frame."""
        return (self.keys.astype(np.float64) + 0.5) * self.resolution_m

    def empty(self) -> np.ndarray:
        """(M,) bool: voxels seen through often enough to be empty space (free space)."""
        if self.occupancy is None:
            return np.zeros(len(self), bool)
        return self.occupancy <= -self.empty_evidence

    def labels(self) -> np.ndarray:
        """(M,) int32 train id per voxel: argmax of sigma, 0 where there is no evidence or the
        voxel is empty space."""
        lab = np.argmax(self.counts, axis=1).astype(np.int32)
        lab[(self.counts.sum(axis=1) <= 0) | self.empty()] = 0
        return lab

    def probabilities(self) -> np.ndarray:
        """(M, C) normalised sigma (zeros where there is no evidence or empty space)."""
        total = self.counts.sum(axis=1, keepdims=True)
        total[self.empty()] = 0.0
        return np.divide(self.counts, total, out=np.zeros_like(self.counts), where=total > 0)

    def point_labels(self, points_world: np.ndarray) -> np.ndarray:
        """(N,) int32 labels of N world points, row i of this snapshot being point i's voxel:
        the voxel's label, split by its class centroids where the map keeps them."""
        lab = self.labels()
        if self.centroids is None or not len(lab):
            return lab
        # (in float64 first: world coordinates may be far from the origin)
        offsets = np.asarray(points_world, np.float64) - self.keys * self.resolution_m
        return split_labels(
            self.counts, self.centroids, offsets, self.centroid_ratio, lab, self.resolution_m
        )

    def subset(self, keep: np.ndarray) -> MapSnapshot:
        """The voxels `keep` selects (a mask or indices), in order."""
        occ = None if self.occupancy is None else self.occupancy[keep]
        cent = None if self.centroids is None else self.centroids[keep]
        return MapSnapshot(
            self.keys[keep],
            self.counts[keep],
            self.t_last[keep],
            self.ell_m[keep],
            self.resolution_m,
            occ,
            self.empty_evidence,
            cent,
            self.centroid_ratio,
        )

    def static_map(self) -> MapSnapshot:
        """The map without its empty voxels: what stays once what moved is gone."""
        return self.subset(~self.empty()) if self.occupancy is not None else self

    def dynamic_layer(self) -> MapSnapshot:
        """The empty voxels, labelled with the class they held before they were seen through
        (trails of what moved); no occupancy, so that `labels` gives that class."""
        gone = self.subset(self.empty())
        gone.occupancy = None
        return gone

    def layers(self) -> tuple[MapSnapshot, MapSnapshot | None]:
        """What a map's exports show: the static map and the dynamic layer apart with free
        space (occupancy), else the whole map and None."""
        if self.occupancy is None:
            return self, None
        return self.static_map(), self.dynamic_layer()

    def confidence(self) -> np.ndarray:
        """(M,) probability of each voxel's label."""
        p = self.probabilities()
        return p[np.arange(len(self)), self.labels()]

    @staticmethod
    def sort_order(keys: np.ndarray) -> np.ndarray:
        return np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
