"""Write a SemanticKITTI sequence as a ROS 2 MCAP recording, the way rosbag2 would store it.

    tisem kitti-to-mcap path/to/semantickitti_08_mini 08_mini.mcap
    tisem kitti-to-mcap path/to/semantickitti_08_mini --out 08_mini.mcap   # the same
    tisem kitti-to-mcap /data/kitti/dataset 08.mcap --sequence 08 --last 99

Topics: `/velodyne_points` (sensor_msgs/msg/PointCloud2, frame `velodyne`: x y z intensity
float32, `label` = the network's raw SemanticKITTI ids from predictions/, `gt_label` = ground
truth raw ids from labels/ when present, uint32 with the instance in the upper 16 bits like the
.label files, or uint16 semantic ids), `/tf` (map -> base_link at every scan stamp) and
`/tf_static` (base_link -> velodyne, a non-identity mount, so the chain is really composed).
Header stamps come from times.txt (or 10 Hz); log times lag 20 ms like a recorder's. zstd
chunks by default. Scan k of the selected range is message k (`map_mcap.py` numbers by it).
The conversion itself is `tisem.io.kitti_mcap.write_kitti_mcap`.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from tisem import cli
from tisem.commands import entry, new_parser
from tisem.extras import require

log = logging.getLogger("tisem.kitti_to_mcap")


def build_parser() -> argparse.ArgumentParser:
    p = new_parser("kitti_to_mcap", __doc__)
    p.add_argument("data", type=Path, help="a sequence folder, or a dataset root with --sequence")
    p.add_argument(
        "out",
        type=Path,
        nargs="?",
        help="the .mcap file to write (with --format rosbag2: the bag folder); or --out",
    )
    p.add_argument(
        "--out",
        dest="out_option",
        type=Path,
        metavar="OUT",
        help="the same as OUT, as the other commands take it",
    )
    p.add_argument(
        "--format",
        choices=("mcap", "rosbag2"),
        default="mcap",
        help="mcap: one .mcap file; rosbag2: a bag folder (metadata.yaml, QoS) for ros2 bag play",
    )
    p.add_argument(
        "--start-time",
        default="0",
        help="added to times.txt: epoch seconds (1700000000.5) or, as a whole "
        "number from 10^12 on, nanoseconds",
    )
    p.add_argument("--ros-distro", default="humble", help="the ROS distro the bag names")
    p.add_argument("--sequence", help="sequence name under a dataset root, e.g. 08")
    p.add_argument(
        "--predictions",
        type=Path,
        metavar="DIR",
        help="the network's label files, when not the sequence's predictions/: a folder of "
        "NNNNNN.label, or a semantic-kitti-api style prediction root",
    )
    p.add_argument("--first", type=int, default=0, help="first scan id (inclusive)")
    p.add_argument("--last", type=int, help="last scan id (inclusive)")
    p.add_argument(
        "--compression",
        choices=("zstd", "lz4", "none"),
        default="zstd",
        help="chunk compression of the recording",
    )
    p.add_argument(
        "--label-type",
        choices=("uint32", "uint16"),
        default="uint32",
        help="uint32: raw id | instance << 16 as in .label files; uint16: raw id only",
    )
    p.add_argument("--topic", default="/velodyne_points", help="the point-cloud topic")
    p.add_argument("--frame-id", default="velodyne", help="the cloud frame (child of base_link)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="store_true", help="also tisem's debug lines")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.out is not None and args.out_option is not None and args.out != args.out_option:
        parser.error(f"two outputs: OUT {args.out} and --out {args.out_option}; give one")
    args.out = args.out if args.out is not None else args.out_option
    if args.out is None:
        parser.error("no output: give the .mcap file (or bag folder) to write, as OUT or --out")
    return args


@entry
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    require("mcap")
    cli.setup_logging(args.verbose)
    from tisem.errors import DatasetError
    from tisem.io.kitti_mcap import write_kitti_mcap
    from tisem.io.stamps import parse_start_time_ns

    try:
        start_time_ns = parse_start_time_ns(args.start_time)
    except ValueError as exc:
        log.error("--start-time: %s", exc)
        return 2
    try:
        result = write_kitti_mcap(
            args.data,
            args.out,
            sequence=args.sequence,
            first=args.first,
            last=args.last,
            compression=args.compression,
            label_type=args.label_type,
            topic=args.topic,
            frame_id=args.frame_id,
            output_format=args.format,
            start_time_ns=start_time_ns,
            ros_distro=args.ros_distro,
            progress=not args.no_progress,
            predictions=args.predictions,
        )
    except (DatasetError, OSError) as exc:  # a bad sequence, or an .mcap it cannot write
        log.error("%s", exc)
        return 2
    print(
        f"wrote {result.path}: {result.scans} scans of sequence {result.sequence} "
        f"({result.size_bytes / 1e6:.1f} MB, {args.compression}), {len(result.skipped)} skipped"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
