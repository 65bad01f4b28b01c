"""The semantic map (and the labelled scans) as a ROS 2 bag that RViz can show.

`write_map_bag` writes a rosbag2 folder holding `sensor_msgs/msg/PointCloud2` messages:
- `/semantic_map` (transient_local, so RViz gets it whenever it subscribes during
  `ros2 bag play`): one cloud of voxel centres in the map frame, fields `x y z` float32, `rgb`
  (the class colour packed as RViz's "RGB8" transformer reads it), `label` uint16 (train id)
  and `probability` float32 (of that label);
- `/semantic_scans` (with scans): each scan in the map frame (so no /tf is needed in RViz with
  the map frame fixed), fields `x y z rgb` (colour of the mapped label), `label` (mapped),
  `input_label` and, with ground truth, `gt_label`;
- `/semantic_map_dynamic` (free space, transient_local): the voxels seen through, as the map;
- `/dynamic_points` (free space, with scans): each scan's points that landed in space seen
  empty, with the fields of `/semantic_scans`.
Every field sits at a 4-byte aligned offset. Clouds are encoded by
`tisem.io.pointcloud2.array_to_ros_cloud`, as everywhere else.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from tisem.io.map_clouds import (
    DYNAMIC_MAP_TOPIC,
    MAP_TOPIC,
    SCANS_TOPIC,
    checked_per_point,
    scan_clouds,
)
from tisem.io.pointcloud2 import pack_rgb
from tisem.io.rosbag_writer import Rosbag2Writer
from tisem.io.stamps import map_stamp_ns, scan_stamp_ns
from tisem.labels import CLASS_COLORS_RGB
from tisem.scan import Scan
from tisem.snapshot import MapSnapshot

MAP_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "rgb", "label", "probability"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
        "offsets": [0, 4, 8, 12, 16, 20],
        "itemsize": 24,
    }
)


def ros_map_points(snapshot: MapSnapshot) -> np.ndarray:
    """The map as a PointCloud2-ready structured array (`MAP_DTYPE`)."""
    labels = snapshot.labels()
    out = np.empty(len(snapshot), MAP_DTYPE)
    centres = snapshot.centers()
    for i, name in enumerate("xyz"):
        out[name] = centres[:, i]
    out["rgb"] = pack_rgb(CLASS_COLORS_RGB[labels])
    out["label"] = labels
    out["probability"] = snapshot.confidence()
    return out


def ros_scan_points(scan: Scan, mapped_labels: np.ndarray) -> np.ndarray:
    """One scan in the map frame with its mapped labels (and colour), input and GT labels."""
    mapped_labels = checked_per_point(scan, mapped_labels, "mapped labels")
    names = ["x", "y", "z", "rgb", "label", "input_label"]
    if scan.gt_labels is not None:
        names.append("gt_label")
    formats = ["<f4"] * 4 + ["<u2"] * (len(names) - 4)
    offsets = [0, 4, 8, 12, 16, 18, 20][: len(names)]
    dtype = np.dtype(
        {
            "names": names,
            "formats": formats,
            "offsets": offsets,
            "itemsize": 24 if scan.gt_labels is not None else 20,
        }
    )
    out = np.empty(scan.num_points, dtype)
    world = scan.points_world()
    for i, name in enumerate("xyz"):
        out[name] = world[:, i]
    out["rgb"] = pack_rgb(CLASS_COLORS_RGB[mapped_labels])
    out["label"] = mapped_labels
    out["input_label"] = scan.labels if scan.labels is not None else np.argmax(scan.probs, axis=1)
    if scan.gt_labels is not None:
        out["gt_label"] = scan.gt_labels
    return out


class MapBag:
    """A rosbag2 folder being filled with the map and scans (module docstring)."""

    def __init__(
        self, folder: str | Path, frame_id: str = "map", *, ros_distro: str = "humble"
    ) -> None:
        self.frame_id = frame_id
        self.scans = 0
        # a map is rewritten like map.npz: the bag of an earlier run in that folder goes
        self._bag = Rosbag2Writer(
            folder,
            ros_distro=ros_distro,
            latched=(MAP_TOPIC, DYNAMIC_MAP_TOPIC),
            overwrite=True,
        )

    def write_map(self, snapshot: MapSnapshot, stamp_ns: int, topic: str = MAP_TOPIC) -> None:
        """The map on `topic` (free space: DYNAMIC_MAP_TOPIC for the voxels seen through)."""
        self._bag.write_cloud(topic, ros_map_points(snapshot), self.frame_id, stamp_ns, stamp_ns)

    def write_scan(
        self, scan: Scan, mapped_labels: np.ndarray, dynamic: np.ndarray | None = None
    ) -> None:
        """A scan with its mapped labels; its points flagged in `dynamic` (free space) also go
        to DYNAMIC_POINTS_TOPIC."""
        t = max(scan_stamp_ns(scan), 0)
        for topic, cloud in scan_clouds(scan, ros_scan_points(scan, mapped_labels), dynamic):
            self._bag.write_cloud(topic, cloud, self.frame_id, t, t, sequence=self.scans)
        self.scans += 1

    def finish(self) -> None:
        self._bag.finish()

    def __enter__(self) -> MapBag:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()


def write_map_bag(
    folder: str | Path,
    snapshot: MapSnapshot,
    frame_id: str = "map",
    scans: Iterable[tuple[Scan, np.ndarray]] | None = None,
    *,
    ros_distro: str = "humble",
) -> dict:
    """Write the map (and optionally the scans with their mapped labels, written as they
    come) as a rosbag2 folder; the map is stamped by `map_stamp_ns`.
    Returns {"path", "voxels", "scans", "map_topic", "scans_topic"}."""
    scans = iter(scans) if scans is not None else iter(())
    first = next(scans, None)
    with MapBag(folder, frame_id, ros_distro=ros_distro) as bag:
        bag.write_map(snapshot, map_stamp_ns(snapshot, first[0] if first else None))
        for scan, mapped in itertools.chain([first] if first is not None else [], scans):
            bag.write_scan(scan, mapped)
    return {
        "path": str(folder),
        "voxels": len(snapshot),
        "scans": bag.scans,
        "map_topic": MAP_TOPIC,
        "scans_topic": SCANS_TOPIC,
    }
