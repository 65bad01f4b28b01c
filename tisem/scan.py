"""`Scan`: the one thing every reader produces and the mapper consumes."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from tisem.errors import ScanError
from tisem.poses import pose_problem


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
    input: str = "predictions"  # which label files fed the map: predictions | labels


@dataclass(frozen=True)
class McapSource(ScanSource):
    """A point cloud read from an MCAP recording."""

    topic: str = ""
    frame_id: str = ""
    stamp_ns: int = 0  # the cloud's header stamp
    log_time_ns: int = 0  # when the recorder logged it


def finite_rows(a: np.ndarray) -> np.ndarray:
    """(N,) bool: which rows of a are all finite. The one rule for non-finite points (the
    mapper drops them, evaluation ignores them). A flat all() first, ~30x cheaper than the
    per-row one, as scans are almost always clean."""
    finite = np.isfinite(a)
    return np.ones(len(a), bool) if finite.all() else finite.all(axis=1)


# A stamp is seconds since any epoch; beyond this it is not a time in seconds (past the year
# 2286 as Unix time: nanoseconds given as seconds, or corrupt data).
MAX_STAMP_S = 1.0e10
# Train ids travel as int32: anything at or above this would wrap when cast.
LABEL_LIMIT = 2**31
# How far a probability may exceed 1 (float16 softmax outputs round up to 1 + 2^-10); a larger
# value is a score or a logit, not a probability, and sums of such values can overflow float32.
PROB_TOLERANCE = 1.0e-3
_NUMERIC = "biuf"  # numpy dtype kinds the arrays of a scan may have (bool, ints, floats)


def scan_label(index: int, name: str = "") -> str:
    """How errors name a scan."""
    return f"scan {index}" + (f" ({name})" if name else "")


def _numeric(values, what: str, where: str) -> np.ndarray:
    a = np.asarray(values)
    if a.dtype.kind not in _NUMERIC:
        raise ValueError(f"{where}: {what} must be numbers, got an array of dtype {a.dtype}")
    return a


def checked_query_points(points_world) -> np.ndarray:
    """Points to look up in a map (not a scan's, but checked by the same rules) as an (N, 3)
    float64 array; ValueError unless they are numbers of that shape (a non-finite point is the
    query's to answer: label 0)."""
    pts = np.asarray(points_world)
    if pts.dtype.kind not in _NUMERIC:
        raise ValueError(f"query points must be numbers, got an array of dtype {pts.dtype}")
    pts = pts.astype(np.float64, copy=False)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"query points must be (N, 3), got {pts.shape}")
    return pts


def checked_ids(values, what: str, where: str, limit: int = LABEL_LIMIT) -> np.ndarray:
    """`values` as an int32 array of ids in [0, limit), checked before the cast, so that no
    value wraps (2^32 + 9 is refused, not read as 9); ValueError naming the first bad one.

    Any integer dtype is taken, and floats that hold whole numbers.
    """
    a = _numeric(values, what, where)
    if a.dtype.kind == "f":
        bad = ~np.isfinite(a) | (a != np.floor(a)) | (a < 0) | (a >= limit)
    elif a.size and (a.min() < 0 or a.max() >= limit):
        bad = (a < 0) | (a >= limit)
    else:
        return np.asarray(a, dtype=np.int32)
    if bad.any():
        i = int(np.flatnonzero(bad.ravel())[0])
        raise ValueError(
            f"{where}: {what} must be whole numbers in [0, {limit}), got "
            f"{a.ravel()[i].item()!r} at point {i}"
        )
    return np.asarray(a, dtype=np.int32)


def checked_probabilities(values, where: str, finite_points: np.ndarray) -> np.ndarray:
    """(N, C) `values` as float32 probabilities, checked before the cast: finite and in [0, 1]
    (within PROB_TOLERANCE) on every finite point (the rows of non-finite points are never
    used). Values above 1 are refused rather than normalised: they are scores or logits given by
    mistake, and rescaling them would hide that and change their weighting."""
    a = _numeric(values, "probabilities", where)
    rows = a if finite_points.all() else a[finite_points]
    if rows.size and not (
        np.isfinite(rows).all() and rows.min() >= 0 and rows.max() <= 1.0 + PROB_TOLERANCE
    ):
        bad = ~np.isfinite(rows) | (rows < 0) | (rows > 1.0 + PROB_TOLERANCE)
        i, c = (int(k[0]) for k in np.nonzero(bad))
        point = i if rows is a else int(np.flatnonzero(finite_points)[i])
        raise ValueError(
            f"{where}: probabilities must be finite and in [0, 1], got "
            f"{rows[i, c].item()!r} at point {point}, class {c}"
        )
    return np.asarray(a, dtype=np.float32)


def checked_stamp(stamp, where: str) -> float:
    """A scan's stamp as float seconds: a real number, finite, |stamp| <= MAX_STAMP_S."""
    if isinstance(stamp, (bool, np.bool_)) or not isinstance(stamp, (numbers.Real, np.number)):
        raise ValueError(f"{where}: stamp_s must be a number of seconds, got {stamp!r}")
    t = float(stamp)
    if not math.isfinite(t) or abs(t) > MAX_STAMP_S:
        raise ValueError(
            f"{where}: stamp_s {t!r} is not a time in seconds (a stamp is finite "
            f"and within +-{MAX_STAMP_S:.0e} s)"
        )
    return t


def checked_pose(T, where: str) -> np.ndarray:
    """T_world_sensor as a (4, 4) float64 array that `tisem.poses.pose_problem` accepts."""
    T = _numeric(T, "T_world_sensor", where)
    problem = pose_problem(T)
    if problem is not None:
        raise ValueError(f"{where}: {problem}")
    return np.asarray(T, dtype=np.float64)


@dataclass
class Scan:
    """One labelled LiDAR scan.

    points_sensor: (N, 3) float32, metres, in the sensor frame.
    labels: (N,) int32 train ids (0 = unlabeled, adds no evidence), or None when `probs` is given.
    probs: (N, C) float32 per-point class probabilities in [0, 1], or None.
    T_world_sensor: (4, 4) float64 pose of the sensor in the world (map) frame: a rotation and
        a plausible position (`tisem.poses.pose_problem`).
    stamp_s: acquisition time in seconds, finite, within +-MAX_STAMP_S.
    gt_labels: (N,) int32 ground-truth train ids, when known (evaluation only).
    moving: (N,) bool, the input's motion labels when it has them (SemanticKITTI's moving ids
        252-259): a moving point is dynamic whatever the map says (tisem.free_space).
    gt_moving: (N,) bool, the ground truth's motion labels, when known (evaluation only).
    index: position in the sequence (scan number); name: a human-readable source (file, topic).
    source: the reader's provenance record (None for scans built by hand).

    Every value is checked here, before any cast (a `ScanError`, a ValueError, naming the scan
    and the value): ids and probabilities of any numeric dtype, a pose, a stamp.
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
    moving: np.ndarray | None = None
    gt_moving: np.ndarray | None = None

    def __post_init__(self) -> None:
        try:
            self._check()
        except ValueError as e:  # (a ScanError: readers report it as a skipped scan)
            raise ScanError(str(e), self.index, self.name) from None

    def _check(self) -> None:
        where = scan_label(self.index, self.name)
        self.points_sensor = np.asarray(
            _numeric(self.points_sensor, "points", where), dtype=np.float32
        )
        if self.points_sensor.ndim != 2 or self.points_sensor.shape[1] != 3:
            raise ValueError(f"{where}: points must be (N, 3), got {self.points_sensor.shape}")
        n = self.points_sensor.shape[0]
        self.T_world_sensor = checked_pose(self.T_world_sensor, where)
        self.stamp_s = checked_stamp(self.stamp_s, where)
        if (self.labels is None) == (self.probs is None):
            raise ValueError(f"{where}: give exactly one of labels or probs")
        if self.labels is not None:
            labels = _numeric(self.labels, "train ids", where)
            if labels.shape != (n,):
                raise ValueError(
                    f"{where}: {labels.shape[0] if labels.ndim else 0} labels for {n} points"
                )
            self.labels = checked_ids(labels, "train ids", where)
        if self.probs is not None:
            probs = _numeric(self.probs, "probabilities", where)
            if probs.ndim != 2 or probs.shape[0] != n:
                raise ValueError(
                    f"{where}: probabilities must be (N, C) with N={n}, got {probs.shape}"
                )
            self.probs = checked_probabilities(probs, where, finite_rows(self.points_sensor))
        if self.gt_labels is not None:
            gt = _numeric(self.gt_labels, "ground-truth train ids", where)
            if gt.shape != (n,):
                raise ValueError(f"{where}: {gt.shape} ground-truth labels for {n} points")
            self.gt_labels = checked_ids(gt, "ground-truth train ids", where)
        for name in ("moving", "gt_moving"):
            flags = getattr(self, name)
            if flags is not None:
                flags = np.asarray(flags)
                if flags.shape != (n,) or flags.dtype.kind not in "biu":
                    raise ValueError(
                        f"{where}: {name} flags must be (N,) booleans with N={n}, "
                        f"got {flags.dtype} {flags.shape}"
                    )
                setattr(self, name, flags.astype(bool, copy=False))

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
