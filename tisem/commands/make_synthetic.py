"""Write a synthetic labelled LiDAR sequence in the SemanticKITTI layout.

    tisem make-synthetic --out data/synth_street --scans 200
    tisem make-synthetic --out data/synth_loop --scans 4000 --route loop
    tisem make-synthetic --out data/robots --scans 300 --robots 3   # one world

The folder gets velodyne/, labels/ (ground truth), predictions/ (noisy "network" labels),
poses.txt (left camera frame), calib.txt (KITTI 08's Tr) and times.txt. With --robots N it is
a dataset root: sequences/00 .. N-1, one per vehicle of one street world, in one world frame
(tisem/synth/fleet_world.py).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from tisem import cli
from tisem.commands import entry, new_parser
from tisem.labels import raw_to_train
from tisem.synth.sequence import ROUTES, write_semantickitti

log = logging.getLogger("tisem.make_synthetic")


def build_parser() -> argparse.ArgumentParser:
    p = new_parser("make_synthetic", __doc__)
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        help="sequence folder to write (new, or without a sequence in it)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the sequence already in --out (its velodyne/, labels/, "
        "predictions/ files and poses.txt, calib.txt, times.txt; nothing else)",
    )
    p.add_argument("--scans", type=int, default=100, help="number of scans (10 Hz, ~1 m apart)")
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the street, its scans and its label noise"
    )
    p.add_argument(
        "--route",
        choices=ROUTES,
        default="street",
        help="street: a straight-ish drive; loop: a long loop that ends past its "
        "start (its length follows --scans)",
    )
    p.add_argument("--points-per-ring", type=int, default=1024, help="azimuth steps per beam")
    p.add_argument(
        "--robots",
        type=int,
        default=1,
        help="vehicles in one world (street route), each its own sequence",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="store_true", help="also tisem's debug lines")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    if args.scans < 1:
        p.error("--scans must be >= 1")
    if args.points_per_ring < 1:
        p.error("--points-per-ring must be >= 1")
    if args.robots < 1 or (args.robots > 1 and args.route != "street"):
        p.error("--robots must be >= 1, and several robots drive the street route")
    return args


def summarize(seq_dir: Path, num_scans: int) -> dict:
    """Points per scan and the noisy labels' accuracy against ground truth, read back from
    the written files (so the summary also checks what a reader will see)."""
    points, correct, total = [], 0, 0
    for i in range(num_scans):
        gt, _ = raw_to_train(np.fromfile(seq_dir / "labels" / f"{i:06d}.label", dtype="<u4"))
        pred, _ = raw_to_train(np.fromfile(seq_dir / "predictions" / f"{i:06d}.label", dtype="<u4"))
        points.append(len(gt))
        correct += int(np.count_nonzero(pred == gt))
        total += len(gt)
    return {
        "scans": num_scans,
        "points_mean": float(np.mean(points)),
        "points_min": int(np.min(points)),
        "points_max": int(np.max(points)),
        "accuracy": correct / max(total, 1),
    }


@entry
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    cli.setup_logging(args.verbose)
    if args.robots > 1:
        return write_robots(args)
    try:
        out = write_semantickitti(
            args.out,
            args.scans,
            seed=args.seed,
            route=args.route,
            points_per_ring=args.points_per_ring,
            progress=not args.no_progress,
            overwrite=args.overwrite,
        )
    except (ValueError, OSError) as exc:
        log.error("%s", exc)
        return 2
    s = summarize(out, args.scans)
    log.info(
        "%s: %d scans (%s, seed %d), %.0f points per scan (%d-%d), noisy-label accuracy "
        "%.4f vs ground truth",
        out,
        s["scans"],
        args.route,
        args.seed,
        s["points_mean"],
        s["points_min"],
        s["points_max"],
        s["accuracy"],
    )
    return 0


def write_robots(args: argparse.Namespace) -> int:
    from tisem.synth.fleet_world import write_fleet

    try:
        folders = write_fleet(
            args.out,
            args.robots,
            args.scans,
            seed=args.seed,
            points_per_ring=args.points_per_ring,
            progress=not args.no_progress,
        )
    except (ValueError, OSError) as exc:
        log.error("%s", exc)
        return 2
    for folder in folders:
        s = summarize(folder, args.scans)
        log.info("%s: %d scans, noisy-label accuracy %.4f", folder, s["scans"], s["accuracy"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
