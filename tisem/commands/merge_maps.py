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
    p.add_argument(
        "--out", type=Path, required=True, help="a new or empty folder for the merged tiled map"
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a previous merge's files in --out (and nothing else there)",
    )
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


# what a merge writes in its folder (tisem.merge_files): --overwrite removes these alone
MERGE_FILES = ("tiles.json", "map.npz", "map.ply", "map_bev.png")


def claim_out(out: Path, inputs: list[Path], overwrite: bool) -> None:
    """--out must be a new or empty folder, or with --overwrite a previous merge's (whose
    files are removed), and never the folder of a map being merged; AppError otherwise."""
    if out.exists() and not out.is_dir():
        raise cli.AppError(f"--out {out}: is a file, not a folder")
    for given in inputs:
        folder = given if given.is_dir() else given.parent
        if folder.resolve() == out.resolve():
            raise cli.AppError(
                f"--out {out}: holds the map {given} being merged, which the merge would "
                f"replace; choose another --out"
            )
    contents = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if not contents:
        return
    shown = ", ".join(contents[:5]) + (", ..." if len(contents) > 5 else "")
    if not overwrite:
        raise cli.AppError(
            f"--out {out}: the folder is not empty ({shown}); give --overwrite to replace a "
            f"previous merge there, or another --out"
        )
    if not (out / MERGE_FILES[0]).is_file():
        raise cli.AppError(
            f"--out {out}: the folder is not empty ({shown}) and holds no merged map (no "
            f"{MERGE_FILES[0]}) for --overwrite to replace; choose another --out"
        )
    removed = [p for p in (out / name for name in MERGE_FILES) if p.is_file()]
    removed += sorted((out / "tiles").glob("tile_*.npz"))
    for path in removed:
        path.unlink()
    log.info("--overwrite: removed %d files of a previous merge from %s", len(removed), out)


def merge(args: argparse.Namespace) -> int:
    from tisem.merge_files import merge_maps

    claim_out(args.out, args.maps, args.overwrite)
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
