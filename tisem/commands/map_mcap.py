"""Map a LiDAR recording (MCAP) whose points carry labels, and write the map as MCAP.

    tisem map-mcap drive.mcap --arch cpu
    tisem map-mcap drive.mcap --topic /ouster/points --label-field class \
           --label-space train
    tisem map-mcap drive.mcap --prob-field probs --pose-topic /odom --map-frame odom
    tisem map-mcap 08.mcap --gt-field gt_label --save-scans      # scores like map_kitti.py
    tisem map-mcap drive.mcap --out results/drive --checkpoint-every 100
    tisem map-mcap --resume results/drive                       # after a crash: go on
    tisem map-mcap drive --static-tf "0.81 -0.32 1.73 0 0 0 1 base_link velodyne"  # no /tf_static

Reads ROS 2 `sensor_msgs/msg/PointCloud2` (cdr) or `foxglove.PointCloud` (protobuf). Poses come
from /tf + /tf_static (map frame -> the cloud's frame_id at the header stamp, interpolated),
or from `--pose-topic` (nav_msgs/Odometry, geometry_msgs/PoseStamped; /tf_static still gives
the sensor mount; `--static-tf "X Y Z QX QY QZ QW PARENT CHILD"` gives a mount the recording
lacks). Damaged files (cut short, bad chunks, no index) are read as far as they
can be; what was lost is printed and written to `mcap_report.json`. The output folder gets
what `map_kitti.py` writes plus `map.mcap` (topic /semantic_map, open it in Foxglove).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from tisem import cli
from tisem.commands import entry, new_parser
from tisem.errors import RunError, os_error_text
from tisem.extras import require
from tisem.logs import read_losses
from tisem.recording_args import add_recording_args
from tisem.recording_args import recording_options as options_from_args

if TYPE_CHECKING:  # (imported when needed: the help stays fast)
    from tisem.io.mcap_reader import McapOptions, McapScanReader
    from tisem.run import RunResult

log = logging.getLogger("tisem.map_mcap")

# the recording options: a resumed run reads the recording as it started (run.json "options")
RECORDING_OPTIONS = {
    "topic": "--topic",
    "label_field": "--label-field",
    "label_space": "--label-space",
    "prob_field": "--prob-field",
    "gt_field": "--gt-field",
    "map_frame": "--map-frame",
    "pose_topic": "--pose-topic",
    "pose_child_frame": "--pose-child-frame",
    "tf_tolerance_ms": "--tf-tolerance-ms",
    "static_tf": "--static-tf",
    "sequence": "--sequence",
}


def build_parser() -> argparse.ArgumentParser:
    p = new_parser("map_mcap", __doc__)
    p.add_argument(
        "log",
        type=Path,
        nargs="?",
        help="the recording: .mcap, a rosbag2 folder, .db3 or ROS 1 .bag (with "
        "--resume: default the one it read)",
    )
    g = add_recording_args(p)
    g.add_argument(
        "--sequence",
        default="00",
        help="sequence name of the predictions folder (sequences/NN/predictions)",
    )
    g.add_argument(
        "--save-scans",
        action="store_true",
        help="also write each scan with its mapped labels into map.mcap and map_ros2/",
    )
    cli.add_run_args(p)
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = cli.parse_run_args(p, argv, kept_on_resume=RECORDING_OPTIONS)
    if args.log is None and args.resume is None:
        p.error("the .mcap recording is required (or --resume DIR)")
    return args


def recording_options(args: argparse.Namespace, plan: cli.RunPlan) -> McapOptions:
    """`McapOptions` from the command line, or those the resumed run read with; the frame
    range and the class count always come from the run's config."""
    from tisem.io.mcap_reader import McapOptions

    cfg = plan.cfg
    frames = dict(first=cfg.first, last=cfg.last, num_classes=cfg.mapper.num_classes)
    if plan.checkpoint is not None:
        stored = plan.source.get("options")
        if stored is None:
            raise cli.AppError("resume: the checkpoint does not say how the recording was read")
        with cli.bad_input("resume: "):
            try:
                options = McapOptions(**{**stored, **frames})
            except TypeError as exc:
                raise ValueError(f"stored recording options: {exc}") from None
            options.validate()
        return options
    with cli.bad_input("options: "):
        return options_from_args(args, **frames)


def map_recording(args: argparse.Namespace) -> int:
    from tisem.io.bag_open import open_scan_reader
    from tisem.report import results_table

    plan = cli.plan_run(args)
    options = recording_options(args, plan)
    path = plan.input_path(args.log, "mcap", "the .mcap recording")
    with cli.bad_input():
        reader = open_scan_reader(path, options)
    notes = set(reader.report.notes)  # how it was read (no CRCs, read linearly): not losses
    for line in reader.report.lines():
        log.log(logging.INFO if line in notes else logging.WARNING, "%s: %s", path.name, line)
    log.info(
        "%s: %d scans on %s (frame %s), poses: %s",
        path,
        reader.total,
        reader.topic,
        reader.frame_id,
        reader.tf.describe(),
    )

    plan.start(args)
    sequence_name = plan.source.get("sequence", "00") if plan.checkpoint else args.sequence
    run = plan.mapping_run(
        reader,
        args,
        sequence_name=sequence_name,
        total=reader.total,
        source_info={
            "mcap": str(path.resolve()),
            "topic": reader.topic,
            "classes": str(plan.classes) if plan.classes else None,
            "frame_id": reader.frame_id,
            "options": vars(options),
            "arch": plan.device,
            "threads": plan.threads,
        },
    )
    result = run.run(show_progress=not args.no_progress)
    out = plan.out_dir
    try:
        map_path = write_map(
            result, reader, out / "map.mcap", args.save_scans, options.map_frame, sequence_name
        )
        (out / "mcap_report.json").write_text(json.dumps(reader.report.to_dict(), indent=2))
    except OSError as exc:
        raise RunError(
            f"cannot write map.mcap / mcap_report.json in {out}: "
            f"{os_error_text(exc)}; metrics.json and the map files are written"
        ) from exc
    print(results_table(result.metrics, per_class=args.per_class))
    # the run has reported each skipped scan once already: here, only what was lost besides
    lines = read_losses(reader)
    if lines:
        # notes alone (rosbag2's chunks without CRCs) are how it was read, not a loss
        intact = set(lines) <= notes
        print(
            f"\n{path.name}: "
            + ("read whole, with these notes:" if intact else "not everything could be used:")
        )
        print("\n".join(f"  - {line}" for line in lines))
    print(
        f"\nmap: {map_path} (Foxglove: 3D panel, topic /semantic_map); ROS 2 bag: "
        f"{out / 'map_ros2'} (ros2 bag play, RViz: fixed frame {options.map_frame})"
        f"\nresults in {out}"
    )
    return plan.finish(result)


def write_map(
    result: RunResult,
    reader: McapScanReader,
    path: Path,
    save_scans: bool,
    frame_id: str,
    sequence_name: str = "00",
) -> Path:
    """map.mcap and map_ros2/ from the final map; with `save_scans`, the log is read once
    more and every mapped scan written with its labels looked up in the final map (the same
    as its predictions file; a scan that was not mapped has neither) and, with free space,
    its dynamic flags (its .dynamic file)."""
    from tisem.io.kitti_predictions import read_dynamic_flags
    from tisem.outputs import write_recording_maps
    from tisem.scan import Scan

    scans = None
    if save_scans:
        scans = (
            (
                s,
                result.mapper.query(s.points_world(), with_probs=False)[0],
                read_dynamic_flags(result.out_dir, sequence_name, s.index, s.num_points),
            )
            for s in reader
            if isinstance(s, Scan) and result.is_mapped(s.index)
        )
    info = write_recording_maps(path.parent, result.mapper.snapshot(), frame_id, scans)
    log.info(
        "wrote %s and %s: %d voxels%s",
        info["mcap"],
        info["bag"],
        info["voxels"],
        f", {info['scans']} labelled scans" if save_scans else "",
    )
    return path


@entry
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    require("mcap")  # --help works without the extra
    return cli.run_app(map_recording, args, log)


if __name__ == "__main__":
    sys.exit(main())
