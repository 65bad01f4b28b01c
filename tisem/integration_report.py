"""What `Mapper.integrate` reports of one scan: what became of its points and of the map."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class IntegrationReport:
    """What happened to one scan's points."""

    points: int = 0
    used: int = 0
    dropped_nonfinite: int = 0
    dropped_range: int = 0
    dropped_band: int = 0  # in range, but outside the height band: unmapped
    dropped_window: int = 0
    dropped_far: int = 0  # of dropped_range: implausibly far (> 1 km), corrupt data
    dropped_dense: int = 0  # a scan too dense for the block cap: points cut away
    training_voxels: int = 0
    evicted_voxels: int = 0
    reloaded_voxels: int = 0
    dynamic_points: int = 0  # free space: points flagged dynamic
    freed_voxels: int = 0  # free space: voxels the scan's rays took evidence from
    seen_empty_blocks: int = 0  # free space: leaf blocks of the memory of space seen empty
    # after its last pass (one every quarter of seen_empty_s)
    dynamic: np.ndarray | None = None  # free space: (points,) bool, which points are dynamic
