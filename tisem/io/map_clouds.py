"""The map and its scans as point clouds: the topics they go on, and the point layouts of the
Foxglove map file.

Apart from the writers because two of them share it: `tisem.io.mcap_writer.write_map_mcap`
(Foxglove) and `tisem.io.rosbag_map` (RViz) put the map and the scans on the same topics, and
`scan_clouds` splits a scan's points between those topics the same way for both. The point
layouts here are Foxglove's; RViz wants colour packed into one `rgb` field, so `rosbag_map`
has its own.
"""

from __future__ import annotations

import numpy as np

from tisem.labels import CLASS_COLORS_RGB
from tisem.scan import Scan
from tisem.snapshot import MapSnapshot

MAP_TOPIC = "/semantic_map"
SCANS_TOPIC = "/semantic_scans"
# free space: the voxels seen through (trails of what moved), apart from the static map, and
# per scan its points that landed in space seen empty
DYNAMIC_MAP_TOPIC = "/semantic_map_dynamic"
DYNAMIC_POINTS_TOPIC = "/dynamic_points"

_RGBA = ("red", "green", "blue", "alpha")
# what every point has: position, the colour of its label (Foxglove colours by "RGBA
# (separate fields)" on its own) and the label (train id)
_POINT = [(c, "<f4") for c in "xyz"] + [(c, "u1") for c in _RGBA] + [("label", "<u2")]


def _fill(out: np.ndarray, xyz: np.ndarray, labels: np.ndarray) -> None:
    """The `_POINT` fields of `out`: positions `xyz`, `labels` and their class colours."""
    for i, name in enumerate("xyz"):
        out[name] = xyz[:, i]
    rgba = np.full((len(labels), 4), 255, dtype=np.uint8)
    rgba[:, :3] = CLASS_COLORS_RGB[labels]
    for i, name in enumerate(_RGBA):
        out[name] = rgba[:, i]
    out["label"] = labels


def map_points(snapshot: MapSnapshot) -> np.ndarray:
    """The map as a structured array: voxel centres, colour, label (train id), probability."""
    out = np.empty(len(snapshot), np.dtype(_POINT + [("probability", "<f4")]))
    _fill(out, snapshot.centers(), snapshot.labels())
    out["probability"] = snapshot.confidence()
    return out


def checked_per_point(scan: Scan, values: np.ndarray, what: str, dtype=None) -> np.ndarray:
    """`values` as an array, when it holds one value per point of `scan`; ValueError saying
    how many `what` it holds otherwise."""
    values = np.asarray(values, dtype)
    if values.shape != (scan.num_points,):
        raise ValueError(f"scan {scan.index}: {values.shape} {what} for {scan.num_points} points")
    return values


def scan_points(scan: Scan, mapped_labels: np.ndarray) -> np.ndarray:
    """One scan in its sensor frame with its mapped labels (colour), input and GT labels."""
    mapped_labels = checked_per_point(scan, mapped_labels, "mapped labels")
    fields = _POINT + [("input_label", "<u2")]
    if scan.gt_labels is not None:
        fields.append(("gt_label", "<u2"))
    out = np.empty(scan.num_points, np.dtype(fields))
    _fill(out, scan.points_sensor, mapped_labels)
    out["input_label"] = scan.labels if scan.labels is not None else np.argmax(scan.probs, axis=1)
    if scan.gt_labels is not None:
        out["gt_label"] = scan.gt_labels
    return out


def scan_clouds(
    scan: Scan, points: np.ndarray, dynamic: np.ndarray | None
) -> list[tuple[str, np.ndarray]]:
    """(topic, cloud) of one scan's points (`points`, one row per point, in either writer's
    layout): all of them on SCANS_TOPIC and, when `dynamic` flags some, those on
    DYNAMIC_POINTS_TOPIC."""
    clouds = [(SCANS_TOPIC, points)]
    if dynamic is not None:
        dynamic = checked_per_point(scan, dynamic, "dynamic flags", bool)
        if dynamic.any():
            clouds.append((DYNAMIC_POINTS_TOPIC, points[dynamic]))
    return clouds
