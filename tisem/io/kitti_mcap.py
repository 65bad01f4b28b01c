"""A SemanticKITTI sequence as a ROS 2 recording: one MCAP file, or a rosbag2 bag folder.

    from tisem.io.kitti_mcap import write_kitti_mcap
    result = write_kitti_mcap("../shared/data/semantickitti_08_mini", "08_mini.mcap")
    result = write_kitti_mcap(seq_dir, "08_bag", output_format="rosbag2",
                              start_time_ns=1_700_000_000_000_000_000)

Topics:
- `/velodyne_points` (sensor_msgs/msg/PointCloud2, frame `velodyne`): x y z intensity float32,
  `label` = the network's raw SemanticKITTI ids from predictions/, `gt_label` = the ground
  truth's raw ids from labels/ when present; uint32 with the instance in the upper 16 bits like
  the .label files, or uint16 semantic ids;
- `/tf`: map -> base_link at every scan stamp;
- `/tf_static`: base_link -> velodyne, a non-identity mount, so the chain is really composed.
Header stamps are `start_time_ns` plus times.txt (or 10 Hz), in integer nanoseconds read from
the decimal text (never through float seconds); log times lag 20 ms like a recorder's. Scan k of
the selected range is message k on the cloud topic (the MCAP reader numbers scans by it). The
bag folder (`tisem.io.rosbag_writer`) adds metadata.yaml, the QoS of every topic
(transient_local for /tf_static) and the ROS distro.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tisem.errors import SkippedScan
from tisem.io.kitti_files import entry_texts
from tisem.io.mcap_writer import Ros2McapWriter
from tisem.io.rosbag_writer import Rosbag2Writer
from tisem.io.semantickitti import SemanticKittiSequence
from tisem.io.stamps import decimal_seconds_to_ns, seconds_to_ns
from tisem.io.tf import invert

log = logging.getLogger(__name__)

# base_link -> velodyne: the KITTI roof mount (1.73 m up, 0.81 m ahead of the rear axle) with a
# small yaw and roll, so that no step of the tf chain is an identity by accident
_YAW, _ROLL = np.deg2rad(1.5), np.deg2rad(-0.7)
T_BASE_VELODYNE = np.array(
    [
        [np.cos(_YAW), -np.sin(_YAW) * np.cos(_ROLL), np.sin(_YAW) * np.sin(_ROLL), 0.81],
        [np.sin(_YAW), np.cos(_YAW) * np.cos(_ROLL), -np.cos(_YAW) * np.sin(_ROLL), -0.32],
        [0.0, np.sin(_ROLL), np.cos(_ROLL), 1.73],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
RECEIVE_LAG_NS = 20_000_000
LABEL_TYPES = {"uint32": "<u4", "uint16": "<u2"}
OUTPUT_FORMATS = ("mcap", "rosbag2")
SCAN_PERIOD_NS = 100_000_000  # 10 Hz when there is no times.txt


@dataclass(frozen=True)
class KittiMcapResult:
    """What `write_kitti_mcap` wrote."""

    path: Path  # the .mcap file, or the bag folder
    scans: int  # clouds written
    skipped: list[SkippedScan]  # scans the SemanticKITTI reader could not use
    sequence: str  # the sequence name
    size_bytes: int  # of every file written


def scan_stamps_ns(seq: SemanticKittiSequence) -> list[int]:
    """Integer-nanosecond stamp of each selected scan, from the text of its times.txt entry
    (None where it is no time: the reader skips that scan anyway), or 10 Hz by scan id."""
    if seq.time_entries is None:
        return [sid * SCAN_PERIOD_NS for sid in seq.scan_ids]
    entries = entry_texts(seq.times_file)
    stamps = []
    for e in seq.time_entries:
        try:
            stamps.append(decimal_seconds_to_ns(entries[e]))
        except (IndexError, ValueError):
            stamps.append(None)
    return stamps


def _field_labels(raw: np.ndarray, label_type: str) -> np.ndarray:
    """A scan's .label values (uint32, one per point: the reader keeps every point) in the
    cloud's label type."""
    return raw if label_type == "uint32" else (raw & 0xFFFF).astype("<u2")


def write_kitti_mcap(
    data: str | Path,
    out: str | Path,
    *,
    sequence: str | None = None,
    first: int = 0,
    last: int | None = None,
    compression: str = "zstd",
    label_type: str = "uint32",
    topic: str = "/velodyne_points",
    frame_id: str = "velodyne",
    output_format: str = "mcap",
    start_time_ns: int = 0,
    ros_distro: str = "humble",
    progress: bool = False,
    predictions: str | Path | None = None,
) -> KittiMcapResult:
    """Write scans `first`..`last` (inclusive scan ids) of a SemanticKITTI sequence.

    data: a sequence folder, or a dataset root with `sequence` (e.g. "08"). compression: zstd |
    lz4 | none. label_type: uint32 (raw id | instance << 16, as in .label files) or uint16
    (raw id only). frame_id: the cloud frame, a child of base_link. output_format: `mcap` (the
    file `out`) or `rosbag2` (the bag folder `out`, for `ros2 bag play`, named after
    `ros_distro`). start_time_ns: added to every stamp (real epoch stamps). progress: a
    progress bar per scan (a whole sequence takes minutes). predictions: the network's label
    files when not the sequence's predictions/ (`SemanticKittiSequence`'s). Raises
    `DatasetError` when the sequence cannot be read, FileExistsError for a bag folder that
    holds a bag.
    """
    if label_type not in LABEL_TYPES:
        raise ValueError(f"label_type must be one of {sorted(LABEL_TYPES)}, got {label_type!r}")
    if output_format not in OUTPUT_FORMATS:
        raise ValueError(f"output_format must be one of {OUTPUT_FORMATS}, got {output_format!r}")
    if not (isinstance(start_time_ns, int) and 0 <= start_time_ns < 2**62):
        raise ValueError(f"start_time_ns must be whole nanoseconds >= 0, got {start_time_ns!r}")
    out = Path(out)
    seq = SemanticKittiSequence(
        data,
        sequence=sequence,
        input="predictions",
        first=first,
        last=last,
        predictions=predictions,
    )
    fields = [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("intensity", "<f4"),
        ("label", LABEL_TYPES[label_type]),
    ]
    if seq.has_ground_truth:
        fields.append(("gt_label", LABEL_TYPES[label_type]))
    T_velodyne_base = invert(T_BASE_VELODYNE)
    written, skipped = 0, []
    out.parent.mkdir(parents=True, exist_ok=True)
    stamps = scan_stamps_ns(seq)
    writer = (
        Rosbag2Writer(out, ros_distro=ros_distro, compression=compression)
        if output_format == "rosbag2"
        else Ros2McapWriter(out, compression=compression)
    )
    with writer as w:
        w.add_metadata(
            "source",
            {
                "sequence_dir": str(seq.sequence_dir),
                "sequence": seq.sequence_name,
                "scan_ids": ",".join(map(str, seq.scan_ids)),
            },
        )
        static_done = False
        scans = tqdm(seq, total=len(seq), unit="scan", desc="kitti-to-mcap", disable=not progress)
        for k, scan in enumerate(scans):
            if isinstance(scan, SkippedScan):
                skipped.append(scan)
                log.warning("skipped scan %s: %s", scan.index, scan.reason)
                continue
            # (a line the reader accepted that is no decimal: cannot happen, but stay exact
            # to the float the reader has rather than fail)
            stamp_ns = start_time_ns + (
                stamps[k] if stamps[k] is not None else seconds_to_ns(scan.stamp_s)
            )
            if not static_done:  # rosbag2 records /tf_static once, latched, at the start
                w.write_transforms(
                    [("base_link", frame_id, stamp_ns, T_BASE_VELODYNE)], stamp_ns, static=True
                )
                static_done = True
            T_map_base = scan.T_world_sensor @ T_velodyne_base
            w.write_transforms([("map", "base_link", stamp_ns, T_map_base)], stamp_ns)
            # intensity and raw label ids come from the files: the Scan holds train ids only
            data_xyzi = np.fromfile(seq.scan_path(k), dtype="<f4").reshape(-1, 4)
            arr = np.empty(scan.num_points, np.dtype(fields))
            arr["x"], arr["y"], arr["z"] = scan.points_sensor.T
            arr["intensity"] = data_xyzi[:, 3]
            n = scan.num_points
            arr["label"] = _field_labels(seq.label_values(k, "predictions", n), label_type)
            if seq.has_ground_truth:
                arr["gt_label"] = _field_labels(seq.label_values(k, "labels", n), label_type)
            w.write_cloud(
                topic, arr, frame_id, stamp_ns, stamp_ns + RECEIVE_LAG_NS, sequence=written
            )
            written += 1
    size = sum(p.stat().st_size for p in out.iterdir()) if out.is_dir() else out.stat().st_size
    return KittiMcapResult(
        path=out, scans=written, skipped=skipped, sequence=seq.sequence_name, size_bytes=size
    )
