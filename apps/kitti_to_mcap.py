"""Write a SemanticKITTI sequence as a ROS 2 MCAP recording, the way rosbag2 would store it.

    python apps/kitti_to_mcap.py ../shared/data/semantickitti_08_mini 08_mini.mcap
    python apps/kitti_to_mcap.py /data/kitti/dataset 08.mcap --sequence 08 --last 99

Topics: `/velodyne_points` (sensor_msgs/msg/PointCloud2, frame `velodyne`: x y z intensity
float32, `label` = the network's raw SemanticKITTI ids from predictions/, `gt_label` = ground
truth raw ids from labels/ when present, uint32 with the instance in the upper 16 bits like the
.label files, or uint16 semantic ids), `/tf` (map -> base_link at every scan stamp) and
`/tf_static` (base_link -> velodyne, a non-identity mount, so the chain is really composed).
Header stamps come from times.txt (or 10 Hz); log times lag 20 ms like a recorder's. zstd
chunks by default. Scan k of the selected range is message k (`map_mcap.py` numbers by it).
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger("kitti_to_mcap")

# base_link -> velodyne: the KITTI roof mount (1.73 m up, 0.81 m ahead of the rear axle) with a
# small yaw and roll, so that no step of the tf chain is an identity by accident
_yaw, _roll = np.deg2rad(1.5), np.deg2rad(-0.7)
T_BASE_VELODYNE = np.array([
    [np.cos(_yaw), -np.sin(_yaw) * np.cos(_roll), np.sin(_yaw) * np.sin(_roll), 0.81],
    [np.sin(_yaw), np.cos(_yaw) * np.cos(_roll), -np.cos(_yaw) * np.sin(_roll), -0.32],
    [0.0, np.sin(_roll), np.cos(_roll), 1.73],
    [0.0, 0.0, 0.0, 1.0]])
RECEIVE_LAG_NS = 20_000_000


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path, help="a sequence folder, or a dataset root with --sequence")
    p.add_argument("out", type=Path, help="the .mcap file to write")
    p.add_argument("--sequence", help="sequence name under a dataset root, e.g. 08")
    p.add_argument("--first", type=int, default=0, help="first scan id (inclusive)")
    p.add_argument("--last", type=int, help="last scan id (inclusive)")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd")
    p.add_argument("--label-type", choices=("uint32", "uint16"), default="uint32",
                   help="uint32: raw id | instance << 16 as in .label files; uint16: raw id only")
    p.add_argument("--topic", default="/velodyne_points")
    p.add_argument("--frame-id", default="velodyne", help="the cloud frame (child of base_link)")
    p.add_argument("-v", "--verbose", action="store_true")
    return p.parse_args(argv)


def _raw_labels(path: Path, label_type: str) -> np.ndarray:
    """The raw .label values, one per point of the scan (the reader keeps every point)."""
    raw = np.fromfile(path, dtype="<u4")
    return raw if label_type == "uint32" else (raw & 0xFFFF).astype("<u2")


def convert(args) -> dict:
    from tisem.errors import SkippedScan
    from tisem.io.mcap_writer import Ros2McapWriter
    from tisem.io.semantickitti import SemanticKittiSequence
    from tisem.io.tf import invert

    seq = SemanticKittiSequence(args.data, sequence=args.sequence, input="predictions",
                                first=args.first, last=args.last)
    label_dtype = "<u4" if args.label_type == "uint32" else "<u2"
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("label", label_dtype)]
    if seq.has_ground_truth:
        fields.append(("gt_label", label_dtype))
    T_velodyne_base = invert(T_BASE_VELODYNE)
    written, skipped = 0, []
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with Ros2McapWriter(args.out, compression=args.compression) as w:
        w.add_metadata("source", {"sequence_dir": str(seq.sequence_dir), "sequence": seq.sequence_name,
                                  "scan_ids": ",".join(map(str, seq.scan_ids))})
        static_done = False
        for k, scan in enumerate(seq):
            if isinstance(scan, SkippedScan):
                skipped.append(scan)
                log.warning("skipped scan %s: %s", scan.index, scan.reason)
                continue
            stamp_ns = int(round(scan.stamp_s * 1e9))
            if not static_done:   # rosbag2 records /tf_static once, latched, at the start
                w.write_transforms([("base_link", args.frame_id, stamp_ns, T_BASE_VELODYNE)],
                                   stamp_ns, static=True)
                static_done = True
            T_map_base = scan.T_world_sensor @ T_velodyne_base
            w.write_transforms([("map", "base_link", stamp_ns, T_map_base)], stamp_ns)
            stem = seq.scan_path(k).stem
            data = np.fromfile(seq.scan_path(k), dtype="<f4").reshape(-1, 4)
            arr = np.empty(scan.num_points, np.dtype(fields))
            arr["x"], arr["y"], arr["z"] = scan.points_sensor.T
            arr["intensity"] = data[:, 3]
            arr["label"] = _raw_labels(seq.predictions_dir / f"{stem}.label", args.label_type)
            if seq.has_ground_truth:
                arr["gt_label"] = _raw_labels(seq.labels_dir / f"{stem}.label", args.label_type)
            w.write_cloud(args.topic, arr, args.frame_id, stamp_ns, stamp_ns + RECEIVE_LAG_NS,
                          sequence=written)
            written += 1
    return {"scans": written, "skipped": skipped, "sequence": seq.sequence_name,
            "path": args.out, "bytes": args.out.stat().st_size}


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    from tisem.errors import DatasetError
    try:
        info = convert(args)
    except DatasetError as exc:
        log.error("%s", exc)
        return 2
    print(f"wrote {info['path']}: {info['scans']} scans of sequence {info['sequence']} "
          f"({info['bytes'] / 1e6:.1f} MB, {args.compression}), {len(info['skipped'])} skipped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
