"""Step 1 of the method on the host: the checks of a scan's evidence, and the numpy selection
of the points the map uses (the reference mapper's; the Taichi mapper's kernels select them).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kernels import layout
from kernels.rasterize import CORRUPT_RANGE_M
from tisem.config import MapperConfig
from tisem.scan import Scan, finite_rows


def scan_label(scan: Scan) -> str:
    """How errors name a scan."""
    return f"scan {scan.index}" + (f" ({scan.name})" if scan.name else "")


@dataclass
class CheckedScan:
    """A scan's points and evidence as the kernels take them."""

    points_sensor: np.ndarray   # (N, 3) float32, C-contiguous; non-finite rows moved far away
    evidence: np.ndarray        # (N,) int32 train ids, or (N, C) float32 probabilities
    use_probs: bool
    dropped_nonfinite: int


def check_scan(scan: Scan, num_classes: int) -> CheckedScan:
    """Check a scan's size and evidence (ValueError naming the scan) and move its non-finite
    points beyond any range, where the kernels drop them without a NaN test (which fast math
    would not honour); they are counted as implausibly far there, which the mapper corrects."""
    where = scan_label(scan)
    if scan.num_points >= layout.MAX_SCAN_POINTS:
        raise ValueError(f"{where}: {scan.num_points:,} points; tisem takes at most "
                         f"{layout.MAX_SCAN_POINTS - 1:,} per scan")
    pts = np.ascontiguousarray(scan.points_sensor, dtype=np.float32)
    finite = finite_rows(pts)
    nonfinite = int(len(pts) - np.count_nonzero(finite))
    if nonfinite:
        pts = pts.copy()
        pts[~finite] = (2.0 * CORRUPT_RANGE_M, 0.0, 0.0)
    if scan.labels is not None:
        labels = np.ascontiguousarray(scan.labels, dtype=np.int32)
        if labels.size and (labels.min() < 0 or labels.max() >= num_classes):
            raise ValueError(f"{where}: train ids must lie in [0, {num_classes}), got "
                             f"[{labels.min()}, {labels.max()}]")
        return CheckedScan(pts, labels, False, nonfinite)
    probs = np.ascontiguousarray(scan.probs, dtype=np.float32)
    if probs.shape[1] != num_classes:
        raise ValueError(f"{where}: {probs.shape[1]} probability columns, "
                         f"the map has {num_classes} classes")
    if not np.all(np.isfinite(probs[finite])) or (probs.size and probs.min() < 0):
        raise ValueError(f"{where}: probabilities must be finite and >= 0")
    if nonfinite:
        probs = np.where(finite[:, None], probs, 0).astype(np.float32)
    return CheckedScan(pts, probs, True, nonfinite)


@dataclass
class SelectedPoints:
    """The points of a scan that the map uses, still in the sensor frame."""

    points_sensor: np.ndarray          # (K, 3) float32
    labels: np.ndarray | None          # (K,) int32 train ids
    probs: np.ndarray | None           # (K, C) float32
    dropped_nonfinite: int
    dropped_range: int


def select_points(scan: Scan, cfg: MapperConfig) -> SelectedPoints:
    """Drop NaN/inf points and points outside the range and height band; check the evidence."""
    where = scan_label(scan)
    pts = scan.points_sensor
    finite = np.all(np.isfinite(pts), axis=1)
    rng = np.linalg.norm(np.where(finite[:, None], pts, 0), axis=1)
    keep = (finite & (rng >= cfg.min_range_m) & (rng <= cfg.max_range_m)
            & (pts[:, 2] >= cfg.min_z_m) & (pts[:, 2] <= cfg.max_z_m))
    labels = probs = None
    if scan.labels is not None:
        labels = scan.labels[keep]
        if labels.size and (labels.min() < 0 or labels.max() >= cfg.num_classes):
            raise ValueError(f"{where}: train ids must lie in [0, {cfg.num_classes}), got "
                             f"[{labels.min()}, {labels.max()}]")
    else:
        if scan.probs.shape[1] != cfg.num_classes:
            raise ValueError(f"{where}: {scan.probs.shape[1]} probability columns, "
                             f"the map has {cfg.num_classes} classes")
        probs = scan.probs[keep]
        if not np.all(np.isfinite(probs)) or (probs.size and probs.min() < 0):
            raise ValueError(f"{where}: probabilities must be finite and >= 0")
    n_finite = int(np.count_nonzero(finite))
    return SelectedPoints(pts[keep], labels, probs, len(pts) - n_finite,
                          n_finite - int(np.count_nonzero(keep)))

