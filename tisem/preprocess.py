"""Step 1 of the method on the host: the checks of a scan's evidence, and the numpy selection
of the points the map uses (the reference mapper's; the Taichi mapper's kernels select them).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tisem.config import MapperConfig
from tisem.kernels import layout
from tisem.kernels.rasterize import CORRUPT_RANGE_M
from tisem.scan import (
    Scan,
    checked_ids,
    checked_pose,
    checked_probabilities,
    finite_rows,
    scan_label,
)


@dataclass
class CheckedScan:
    """A scan's points and evidence as the kernels take them."""

    points_sensor: np.ndarray  # (N, 3) float32; non-finite rows moved far away
    evidence: np.ndarray  # (N,) int32 train ids, or (N, C) float32 probabilities
    use_probs: bool
    dropped_nonfinite: int
    # the points as kernels take them: C-contiguous float32 (N, k >= 3), the points in its
    # first three columns (`kernel_rows`); always derived, so `dataclasses.replace` keeps it so
    kernel_points: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.kernel_points = kernel_rows(self.points_sensor)

    def subset(self, keep: np.ndarray) -> CheckedScan:
        """Only the points where `keep` (bool, (N,)) is set, in their order; none of them
        non-finite (the caller keeps only points the kernels located)."""
        return CheckedScan(
            np.ascontiguousarray(self.points_sensor[keep]),
            np.ascontiguousarray(self.evidence[keep]),
            self.use_probs,
            0,
        )


def kernel_array(a: np.ndarray, dtype=None) -> np.ndarray:
    """`a` (in `dtype`) as the kernels may take it: C-contiguous, aligned and in writeable
    memory, copied only where it is not. A CUDA launch copies every host array to the device
    and back after the kernel, whether the kernel wrote to it or not: read-only memory (a
    read-only mmap, bytes) would be written."""
    flags = a.flags
    if (
        (dtype is None or a.dtype == dtype)
        and flags.c_contiguous
        and flags.aligned
        and flags.writeable
    ):
        return a
    return np.array(a, dtype=dtype, order="C")


def kernel_rows(points: np.ndarray) -> np.ndarray:
    """(N, 3) float32 points as a C-contiguous float32 (N, k >= 3) array whose first three
    columns they are. Points that are the first columns of wider rows in one block of writeable
    memory (the KITTI reader's view of its x y z intensity rows) are passed as those rows, not
    copied: a copy of a scan's 1.5 MB costs ~1 ms a scan, mostly the page faults of new memory.
    Elsewhere `kernel_array`."""
    pts, owner = points, points.base
    row_bytes, start = pts.strides[0], pts.ctypes.data
    if (
        pts.dtype == np.float32
        and len(pts) > 0
        and pts.strides[1] == 4
        and row_bytes % 4 == 0
        and 12 < row_bytes <= 64
        and start % 4 == 0
        and isinstance(owner, np.ndarray)
        and owner.flags.c_contiguous
        and owner.flags.writeable
    ):
        low = owner.ctypes.data
        high = low + owner.nbytes
        if low <= start and start + len(pts) * row_bytes <= high:  # the wider rows exist
            return np.lib.stride_tricks.as_strided(
                pts, shape=(len(pts), row_bytes // 4), strides=(row_bytes, 4), writeable=False
            )
    return kernel_array(pts, np.float32)


def check_scan(scan: Scan, num_classes: int) -> CheckedScan:
    """Check a scan's size, pose and evidence again (a Scan's fields can be replaced after it
    was built; ValueError naming the scan) and move its non-finite points beyond any range,
    where the kernels drop them without a NaN test (which fast math would not honour); they
    are counted as implausibly far there, which the mapper corrects."""
    where = scan_label(scan.index, scan.name)
    if scan.num_points >= layout.MAX_SCAN_POINTS:
        raise ValueError(
            f"{where}: {scan.num_points:,} points; tisem takes at most "
            f"{layout.MAX_SCAN_POINTS - 1:,} per scan"
        )
    checked_pose(scan.T_world_sensor, where)
    pts = np.asarray(scan.points_sensor, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{where}: points must be (N, 3), got {pts.shape}")
    finite = finite_rows(pts)
    nonfinite = int(len(pts) - np.count_nonzero(finite))
    if nonfinite:
        pts = np.array(pts, order="C")
        pts[~finite] = (2.0 * CORRUPT_RANGE_M, 0.0, 0.0)
    if (scan.labels is None) == (scan.probs is None):
        raise ValueError(f"{where}: give exactly one of labels or probs")
    if scan.labels is not None:
        if np.shape(scan.labels) != (len(pts),):
            raise ValueError(f"{where}: {np.shape(scan.labels)} labels for {len(pts)} points")
        labels = kernel_array(checked_ids(scan.labels, "train ids", where, num_classes))
        return CheckedScan(pts, labels, False, nonfinite)
    if np.shape(scan.probs) != (len(pts), num_classes):
        raise ValueError(
            f"{where}: probabilities of shape {np.shape(scan.probs)}; the map "
            f"has {num_classes} classes, the scan {len(pts)} points"
        )
    probs = kernel_array(checked_probabilities(scan.probs, where, finite))
    if nonfinite:
        probs = np.where(finite[:, None], probs, 0).astype(np.float32)
    return CheckedScan(pts, probs, True, nonfinite)


@dataclass
class SelectedPoints:
    """The points of a scan that the map uses, still in the sensor frame."""

    points_sensor: np.ndarray  # (K, 3) float32
    labels: np.ndarray | None  # (K,) int32 train ids
    probs: np.ndarray | None  # (K, C) float32
    dropped_nonfinite: int
    dropped_range: int


def select_points(scan: Scan, cfg: MapperConfig) -> SelectedPoints:
    """Drop NaN/inf points and points outside the range and height band; check the evidence."""
    where = scan_label(scan.index, scan.name)
    pts = scan.points_sensor
    finite = np.all(np.isfinite(pts), axis=1)
    rng = np.linalg.norm(np.where(finite[:, None], pts, 0), axis=1)
    keep = (
        finite
        & (rng >= cfg.min_range_m)
        & (rng <= cfg.max_range_m)
        & (pts[:, 2] >= cfg.min_z_m)
        & (pts[:, 2] <= cfg.max_z_m)
    )
    labels = probs = None
    if scan.labels is not None:
        labels = scan.labels[keep]
        if labels.size and (labels.min() < 0 or labels.max() >= cfg.num_classes):
            raise ValueError(
                f"{where}: train ids must lie in [0, {cfg.num_classes}), got "
                f"[{labels.min()}, {labels.max()}]"
            )
    else:
        if scan.probs.shape[1] != cfg.num_classes:
            raise ValueError(
                f"{where}: {scan.probs.shape[1]} probability columns, "
                f"the map has {cfg.num_classes} classes"
            )
        probs = scan.probs[keep]
        if not np.all(np.isfinite(probs)) or (probs.size and probs.min() < 0):
            raise ValueError(f"{where}: probabilities must be finite and >= 0")
    n_finite = int(np.count_nonzero(finite))
    return SelectedPoints(
        pts[keep], labels, probs, len(pts) - n_finite, n_finite - int(np.count_nonzero(keep))
    )
