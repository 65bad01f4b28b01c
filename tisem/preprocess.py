"""Step 1 of the method, shared by the Taichi mapper and the numpy reference."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tisem.config import MapperConfig
from tisem.scan import Scan


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
    where = f"scan {scan.index}" + (f" ({scan.name})" if scan.name else "")
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

