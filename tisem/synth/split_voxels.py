"""Where inside a voxel a network puts each class: the statistic behind the class centroids.

In a 0.2 m voxel that holds two classes of the network's labels, each with a fair share of the
points (the second at least half the first), a point can take the voxel's leading class or the
class whose points lie nearer it inside the voxel (the rule of kernels/centroids.py). Which
answers the ground truth more often tells whether the network's labels say where a class
boundary runs through the voxel: a real network's mostly do, at a curb or a car's edge; noise in
patches that cut voxels anywhere does not. `benchmarks/noise_calibration.py` measures it on the
real frames and on the synthetic streets, per scan in the sensor frame.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from tisem.labels import raw_to_train

VOXEL_M = 0.2
SECOND_SHARE = 0.5  # the second class's points, at least this share of the first's


@dataclass
class SplitVoxels:
    """Points in split voxels, and how many of them the leading class and the nearer class
    get right."""

    points: int = 0
    leading_right: int = 0
    nearer_right: int = 0

    def counting(self, scans: Iterable, max_range_m: float = 50.0) -> Iterator:
        """The scans (`tisem.synth.calibration.LabelledScan`), each counted as it passes."""
        for scan in scans:
            gt, _ = raw_to_train(scan.gt_raw)
            keep = (gt > 0) & (np.linalg.norm(scan.points, axis=1) <= max_range_m)
            self.add(scan.points[keep], gt[keep], scan.pred_train[keep])
            yield scan

    def add(self, points: np.ndarray, gt: np.ndarray, pred: np.ndarray) -> None:
        keys = np.floor(points / VOXEL_M).astype(np.int64)
        voxel = np.unique(keys, axis=0, return_inverse=True)[1].reshape(-1)
        classes = int(max(pred.max(initial=0), gt.max(initial=0))) + 1
        pair = voxel * classes + pred
        ids, pair_of, n = np.unique(pair, return_inverse=True, return_counts=True)
        pair_of = pair_of.reshape(-1)
        # per voxel its two largest classes: pairs sorted by voxel, then by count down
        v, c = ids // classes, ids % classes
        order = np.lexsort((-n, v))
        first = np.r_[True, v[order][1:] != v[order][:-1]]
        lead = order[first]
        second = order[1:][~first[1:] & first[:-1]]  # the pair right after a voxel's first
        v2 = v[second]
        split = np.zeros(v.max() + 1 if len(v) else 0, bool)
        top = np.zeros_like(split, dtype=np.int64)
        top[v[lead]] = n[lead]
        split[v2] = n[second] >= SECOND_SHARE * top[v2]
        # the centroid of every (voxel, class) pair, then per point the nearer of its voxel's two
        centroid = (
            np.stack([np.bincount(pair_of, points[:, a], len(ids)) for a in range(3)], axis=1)
            / n[:, None]
        )
        lead_of = np.full(len(split), -1)
        lead_of[v[lead]] = lead
        second_of = np.full(len(split), -1)
        second_of[v2] = second
        at = split[voxel]
        p, a, b = points[at], lead_of[voxel[at]], second_of[voxel[at]]
        nearer_b = np.square(p - centroid[b]).sum(1) < np.square(p - centroid[a]).sum(1)
        nearer = np.where(nearer_b, c[b], c[a])
        self.points += int(at.sum())
        self.leading_right += int((gt[at] == c[a]).sum())
        self.nearer_right += int((gt[at] == nearer).sum())

    def shares(self) -> tuple[float, float]:
        """(leading class right, nearer class right), shares of the points in split voxels."""
        if not self.points:
            return float("nan"), float("nan")
        return self.leading_right / self.points, self.nearer_right / self.points
