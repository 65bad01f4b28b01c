"""Map a LiDAR recording (MCAP) whose points carry labels, and write the map as MCAP.

    python apps/map_mcap.py drive.mcap --arch cpu
    python apps/map_mcap.py drive.mcap --topic /ouster/points --label-field class --label-space train
    python apps/map_mcap.py drive.mcap --prob-field probs --pose-topic /odom --map-frame odom
    python apps/map_mcap.py 08.mcap --gt-field gt_label --save-scans      # scores like map_kitti.py

Reads ROS 2 `sensor_msgs/msg/PointCloud2` (cdr) or `foxglove.PointCloud` (protobuf). Poses come
from /tf + /tf_static (map frame -> the cloud's frame_id at the header stamp, interpolated),
or from `--pose-topic` (nav_msgs/Odometry, geometry_msgs/PoseStamped; /tf_static still gives
the sensor mount). Damaged files (cut short, bad chunks, no index) are read as far as they
can be; what was lost is printed and written to `mcap_report.json`. The output folder gets
what `map_kitti.py` writes plus `map.mcap` (topic /semantic_map, open it in Foxglove).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from tisem import cli

log = logging.getLogger("map_mcap")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("log", type=Path, help="the .mcap recording")
    g = p.add_argument_group("recording")
    g.add_argument("--topic", help="point-cloud topic (needed only when there are several)")
    g.add_argument("--label-field", default="label", help="per-point label field (default label)")
    g.add_argument("--label-space", choices=("raw", "train"), default="raw",
                   help="label values are raw SemanticKITTI ids (default) or train ids 0..19")
    g.add_argument("--prob-field", help="a count=C float field of class probabilities "
                                        "(instead of --label-field)")
    g.add_argument("--gt-field", help="ground-truth label field (same label space): score the map")
    g.add_argument("--map-frame", default="map", help="the fixed frame of the map (default map)")
    g.add_argument("--pose-topic", help="Odometry / PoseStamped topic instead of /tf")
    g.add_argument("--pose-child-frame", help="the frame a PoseStamped is the pose of (default: "
                                              "the top of the cloud frame's /tf_static chain, "
                                              "e.g. base_link, or the cloud frame itself)")
    g.add_argument("--tf-tolerance-ms", type=float, default=0.0,
                   help="accept a stamp this far outside a transform's samples (default 0)")
    g.add_argument("--sequence-name", default="00",
                   help="sequence folder name for the predictions (default 00)")
    g.add_argument("--save-scans", action="store_true",
                   help="also write each scan with its mapped labels into map.mcap")
    cli.add_common_args(p)
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    cli.setup_logging(args.verbose)
    from tisem.errors import DatasetError
    from tisem.io.mcap_reader import McapOptions, McapScanReader

    try:
        cfg = cli.run_config_from_args(args)
        options = McapOptions(
            topic=args.topic, label_field=args.label_field, label_space=args.label_space,
            prob_field=args.prob_field, gt_field=args.gt_field, map_frame=args.map_frame,
            pose_topic=args.pose_topic, pose_child_frame=args.pose_child_frame,
            tf_tolerance_s=args.tf_tolerance_ms / 1e3, first=cfg.first, last=cfg.last,
            num_classes=cfg.mapper.num_classes)
        options.validate()
    except (KeyError, ValueError, OSError) as exc:
        log.error("options: %s", exc)
        return 2
    try:
        reader = McapScanReader(args.log, options)
    except DatasetError as exc:
        log.error("%s", exc)
        return 2
    for line in reader.report.lines():
        log.warning("%s: %s", args.log.name, line)
    log.info("%s: %d scans on %s (frame %s), poses: %s", args.log, reader.total, reader.topic,
             reader.frame_id, reader.tf.describe())

    from tisem.pipeline import results_table, run_pipeline
    out = cli.results_dir(args)
    try:
        device = cli.init_backend(args)
    except cli.BackendError as exc:
        log.error("%s", exc)
        return 2
    result = run_pipeline(reader, cfg, out, sequence_name=args.sequence_name, total=reader.total,
                          progress=not args.no_progress,
                          source_info={"mcap": str(args.log.resolve()), "topic": reader.topic,
                                       "frame_id": reader.frame_id, "options": vars(options),
                                       "arch": device, "threads": args.threads})
    map_path = write_map(result, reader, out / "map.mcap", args.save_scans, args.map_frame)
    (out / "mcap_report.json").write_text(json.dumps(reader.report.to_dict(), indent=2))
    print(results_table(result.metrics))
    lines = reader.report.lines()
    if lines:
        print(f"\n{args.log.name}: not everything could be used:")
        print("\n".join(f"  - {line}" for line in lines))
    print(f"\nmap: {map_path} (Foxglove: 3D panel, topic /semantic_map)\nresults in {out}")
    return 0


def write_map(result, reader, path: Path, save_scans: bool, frame_id: str) -> Path:
    """map.mcap from the final map; with `save_scans`, the log is read once more and every scan
    written with its labels looked up in the final map (the same as its predictions file)."""
    from tisem.io.mcap_writer import write_map_mcap
    from tisem.scan import Scan

    scans = None
    if save_scans:
        scans = ((s, result.mapper.query(s.points_world(), with_probs=False)[0])
                 for s in reader if isinstance(s, Scan))
    info = write_map_mcap(path, result.mapper.snapshot(), frame_id=frame_id, scans=scans)
    log.info("wrote %s: %d voxels, %d scans", path, info["voxels"], info["scans"])
    return path


if __name__ == "__main__":
    sys.exit(main())
