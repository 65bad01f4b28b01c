"""`Scan`: the one thing every reader produces and the mapper consumes."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ScanSource:
    """Where a scan came from and what its reader made of its labels (typed provenance).

    unknown_raw_ids / unknown_gt_ids: label values the reader could not map to a train id
    (they became 0, no evidence), in the input labels and in the ground truth.
    """

    unknown_raw_ids: int = 0
    unknown_gt_ids: int = 0


@dataclass(frozen=True)
class KittiSource(ScanSource):
    """A scan read from a SemanticKITTI sequence folder."""

    sequence: str = ""
    input: str = "predictions"     # which label files fed the map: predictions | labels


@dataclass(frozen=True)
class McapSource(ScanSource):
    """A point cloud read from an MCAP recording."""

    topic: str = ""
    frame_id: str = ""
    stamp_ns: int = 0              # the cloud's header stamp
    log_time_ns: int = 0           # when the recorder logged it


def finite_rows(a: np.ndarray) -> np.ndarray:
    """(N,) bool: which rows of a are all finite. The one rule for non-finite points (the
    mapper drops them, evaluation ignores them). A flat all() first, ~30x cheaper than the
    per-row one, as scans are almost always clean."""
    finite = np.isfinite(a)
    return np.ones(len(a), bool) if finite.all() else finite.all(axis=1)


@dataclass
class Scan:
    """One labelled LiDAR scan.

    points_sensor: (N, 3) float32, metres, in the sensor frame.
    labels: (N,) int32 train ids (0 = unlabeled, adds no evidence), or None when `probs` is given.
    probs: (N, C) float32 per-point class probabilities, or None.
    T_world_sensor: (4, 4) float64 pose of the sensor in the world (map) frame.
    stamp_s: acquisition time in seconds.
    gt_labels: (N,) int32 ground-truth train ids, when known (evaluation only).
    index: position in the sequence (scan number); name: a human-readable source (file, topic).
    source: the reader's provenance record (None for scans built by hand).
    """

    points_sensor: np.ndarray
    T_world_sensor: np.ndarray
    stamp_s: float
    labels: np.ndarray | None = None
    probs: np.ndarray | None = None
    gt_labels: np.ndarray | None = None
    index: int = 0
    name: str = ""
    source: ScanSource | None = None

    def __post_init__(self) -> None:
        self.points_sensor = np.asarray(self.points_sensor, dtype=np.float32)
        self.T_world_sensor = np.asarray(self.T_world_sensor, dtype=np.float64)
        n = self.points_sensor.shape[0] if self.points_sensor.ndim == 2 else -1
        where = f"scan {self.index}" + (f" ({self.name})" if self.name else "")
        if self.points_sensor.ndim != 2 or self.points_sensor.shape[1] != 3:
            raise ValueError(f"{where}: points must be (N, 3), got {self.points_sensor.shape}")
        if self.T_world_sensor.shape != (4, 4):
            raise ValueError(f"{where}: T_world_sensor must be 4x4, got {self.T_world_sensor.shape}")
        if not np.all(np.isfinite(self.T_world_sensor)):
            raise ValueError(f"{where}: pose has NaN/inf entries")
        if (self.labels is None) == (self.probs is None):
            raise ValueError(f"{where}: give exactly one of labels or probs")
        if self.labels is not None:
            self.labels = np.asarray(self.labels, dtype=np.int32)
            if self.labels.shape != (n,):
                raise ValueError(f"{where}: {self.labels.shape[0] if self.labels.ndim else 0} labels "
                                 f"for {n} points")
        if self.probs is not None:
            self.probs = np.asarray(self.probs, dtype=np.float32)
            if self.probs.ndim != 2 or self.probs.shape[0] != n:
                raise ValueError(f"{where}: probabilities must be (N, C) with N={n}, "
                                 f"got {self.probs.shape}")
        if self.gt_labels is not None:
            self.gt_labels = np.asarray(self.gt_labels, dtype=np.int32)
            if self.gt_labels.shape != (n,):
                raise ValueError(f"{where}: {self.gt_labels.shape} ground-truth labels for {n} points")

    @property
    def num_points(self) -> int:
        return int(self.points_sensor.shape[0])

    def points_world(self) -> np.ndarray:
        """(N, 3) float64 points in the world frame."""
        return to_frame(self.points_sensor, self.T_world_sensor)


def to_frame(points: np.ndarray, T: np.ndarray, offset_m: np.ndarray | None = None) -> np.ndarray:
    """float64 points transformed by T (then shifted by -offset_m, to a local origin).

    `einsum` (its own loops), not `points @ R.T`: a matrix product goes to BLAS, whose worker
    threads keep spinning after it returns and take the cores from Taichi's. Measured on 2
    cores, the real scans replayed with a query after each (benchmarks/throughput.py, three
    alternating runs): mapping took 147 ms per scan after the BLAS product, 134 ms after this."""
    t = T[:3, 3] if offset_m is None else T[:3, 3] - offset_m
    R = np.asarray(T[:3, :3], dtype=np.float64)
    return np.einsum("ij,kj->ik", np.asarray(points, dtype=np.float64), R) + t
