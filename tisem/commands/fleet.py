"""Map many logs (or one long log in time chunks) on Ray and merge their maps.

    tisem fleet data/robots --mode bki --out results/fleet
    tisem fleet /data/kitti/dataset --sequences 00 05 08 --out results/kitti
    tisem fleet long_drive/ --chunks 8 --overlap-scans 40 --threads 2
    tisem fleet bags/*.mcap --world-frame map --address auto   # join a cluster
    tisem fleet robot1/ robot2.db3 old.bag --gt-field gt_label \
           --static-tf "0.8 0 1.7 0 0 0 1 base_link velodyne"     # recordings, scored

LOG: a SemanticKITTI dataset root or sequence folder, or a recording (an .mcap, .db3 or ROS 1
.bag file, a rosbag2 folder), each read with the recording options (those of `tisem map-mcap`).
Each log or chunk is one Ray task in its own process (its kernel threads as its CPUs); the
maps of logs in one world frame are merged by sharded reducers into the tiled map
`<out>/maps/<frame>/` (plus map.npz and friends when it fits), scored against the logs'
ground truth, and fleet.json says what every task did and what is missing. Without
--address, Ray starts a local cluster on this machine's cores (--num-cpus).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from tisem import cli
from tisem.commands import entry, new_parser
from tisem.extras import require
from tisem.ray_cli import add_cluster_args, add_config_args, results_folder
from tisem.recording_args import add_recording_args, recording_options

log = logging.getLogger("tisem.fleet")


def build_parser() -> argparse.ArgumentParser:
    p = new_parser("fleet", __doc__)
    p.add_argument(
        "logs",
        nargs="+",
        type=Path,
        metavar="LOG",
        help="a SemanticKITTI dataset root or sequence folder, or a recording: an .mcap, "
        ".db3 or ROS 1 .bag file, a rosbag2 folder (one or more)",
    )
    add_config_args(p)
    add_recording_args(p)
    p.add_argument("--chunks", type=int, default=1, help="cut every log into N time chunks")
    p.add_argument(
        "--overlap-scans",
        type=int,
        default=20,
        help="warm-up scans a chunk maps before its first one",
    )
    p.add_argument(
        "--refine",
        choices=("auto", "on", "off"),
        default="auto",
        help="map tasks again seeded with the maps of the tasks before them "
        "(auto: in the kernel modes)",
    )
    p.add_argument("--reducers", type=int, default=2, help="reducer tasks (tile shards)")
    p.add_argument("--world-frame", help="all logs' poses are in this one frame")
    p.add_argument(
        "--max-merged-voxels",
        type=int,
        default=20_000_000,
        help="also write map.npz / map.ply / map_bev.png up to this many voxels",
    )
    p.add_argument("--no-eval", action="store_true", help="do not score the merged maps")
    add_cluster_args(p)
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def fleet(args: argparse.Namespace) -> int:
    from tisem.fleet import FleetOptions, run_fleet
    from tisem.fleet_report import recording_losses
    from tisem.logs import discover_logs

    with cli.bad_input("config: "):
        cfg = cli.run_config_from_args(argparse.Namespace(**vars(args), first=None, last=None))
        options = FleetOptions(
            chunks=args.chunks,
            overlap_scans=args.overlap_scans,
            refine={"auto": None, "on": True, "off": False}[args.refine],
            reducers=args.reducers,
            threads=args.threads or 1,
            retries=args.retries,
            address=args.address,
            num_cpus=args.num_cpus,
            arch=args.arch,
            max_merged_voxels=args.max_merged_voxels,
            evaluate=not args.no_eval,
            world_frame=args.world_frame,
            progress=not args.no_progress,
        )
        options.validate()
    with cli.bad_input("options: "):
        recording = recording_options(args)
    with cli.bad_input():
        logs = discover_logs([p.resolve() for p in args.logs], args.sequences, recording)
    out = results_folder(args.out)
    result = run_fleet(logs, cfg, out, options)
    report = result.report
    mapped = {summary["task"]["group"] for summary in report["tasks"].values()}
    for group, folder in result.maps.items():
        if group not in mapped:  # (its index says so too: no task, no voxel)
            print(f"{group}: nothing mapped, every task of it failed (below)")
            continue
        m = report["metrics"].get(group)
        score = (
            f"mIoU {m['final']['miou']:.4f}, accuracy {m['final']['accuracy']:.4f} "
            f"(network {m['input']['miou']:.4f} / {m['input']['accuracy']:.4f})"
            if m and m["scans"]
            else "not scored"
        )
        print(f"{group}: {folder} — {score}")
    for task, reason in result.failed.items():
        print(f"FAILED {task}: {reason}")
    for path, lost in recording_losses(report["tasks"]).items():
        for _, line in lost:
            print(f"{Path(path).name}: {line}")
    missing = report["missing"]
    print(
        f"\n{len(report['tasks'])} tasks mapped, {len(result.failed)} failed, "
        f"{len(missing)} gaps; {sum(report['seconds'].values()):.0f} s; fleet.json in {out}"
    )
    return 1 if result.failed else 0


@entry
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    require("ray")  # --help works without the extra
    return cli.run_app(fleet, args, log)


if __name__ == "__main__":
    sys.exit(main())
