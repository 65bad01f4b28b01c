"""Merge maps built apart (results folders, map.npz files, tiled maps) into one tiled map.

    tisem merge-maps results/robot0 results/robot1 --out results/merged
    tisem merge-maps a/map.npz b/ --out merged --transform 1=12.5,-3,0,90

Per voxel the counters are decayed to the voxel's latest update and summed (tisem.merge).
The maps must share resolution and label space, and a world frame (tisem.merge_files says how
a map's frame is known); a map in another frame needs `--transform K=...`, the transform from
the K-th map's frame (K counts from 0, the first map is the reference) into the first's:
tx,ty,tz[,yaw_deg], 12 or 16 numbers row-major, or a file holding them.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from tisem import cli
from tisem.commands import entry, new_parser

log = logging.getLogger("tisem.merge_maps")


def build_parser() -> argparse.ArgumentParser:
    p = new_parser("merge_maps", __doc__)
    p.add_argument(
        "maps",
        nargs="+",
        type=Path,
        metavar="MAP",
        help="a results folder, a map.npz or a tiled map folder",
    )
    p.add_argument("--out", type=Path, required=True, help="folder of the merged tiled map")
    p.add_argument(
        "--transform",
        action="append",
        default=[],
        metavar="K=T",
        help="transform of map K into the first map's frame (repeatable)",
    )
    p.add_argument(
        "--max-merged-voxels",
        type=int,
        default=20_000_000,
        help="also write map.npz / map.ply / map_bev.png up to this many voxels",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="store_true", help="also tisem's debug lines")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def parse_transforms(given: list[str]) -> dict:
    from tisem.merge_files import parse_transform

    transforms = {}
    for text in given:
        key, sep, value = text.partition("=")
        if not sep or not key.strip().isdigit():
            raise cli.AppError(f"--transform expects K=T with K a map's position, got {text!r}")
        transforms[int(key)] = parse_transform(value)
    return transforms


def merge(args: argparse.Namespace) -> int:
    from tisem.merge_files import merge_maps

    with cli.bad_input():
        result = merge_maps(
            args.maps,
            args.out,
            transforms=parse_transforms(args.transform),
            max_merged_voxels=args.max_merged_voxels,
            progress=not args.no_progress,
        )
    print(
        f"merged {len(args.maps)} maps: {result.voxels:,} voxels in {result.tiles} tiles, "
        f"{result.seconds:.1f} s -> {result.out_dir}"
    )
    return 0


@entry
def main(argv: list[str] | None = None) -> int:
    return cli.run_app(merge, parse_args(argv), log)


if __name__ == "__main__":
    sys.exit(main())
