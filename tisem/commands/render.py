"""Render pictures of a tisem results folder.

    tisem render RESULTS_DIR [--region x0 y0 x1 y1] [--scan N] [--out FILE]
    tisem render RESULTS_DIR --bev [--out FILE]

Default: the 3-panel comparison (network labels | map | ground truth, or without ground truth
the points where the map changed the network's label) of a 40 m square around the middle of
the trajectory, written to RESULTS_DIR/compare.png. `--bev` instead re-draws the
top-down map picture from RESULTS_DIR/map.npz (default RESULTS_DIR/map_bev.png), e.g. after a
resumed run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tisem.commands import EXIT_BAD_INPUT, entry, new_parser
from tisem.extras import require


def _bev(results_dir: Path, out: Path | None) -> int:
    from tisem.io.mapfile import load_map_file
    from tisem.viz.bev import render_bev

    snapshot, _, meta = load_map_file(results_dir / "map.npz")
    trajectory = meta.get("trajectory_xy")  # present when the pipeline stored it
    out = out or results_dir / "map_bev.png"
    cell = render_bev(snapshot, out, trajectory_xy=trajectory, title=results_dir.name)
    print(f"wrote {out} ({len(snapshot)} voxels, cell {cell:g} m)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = new_parser("render", __doc__)
    parser.add_argument("results_dir", type=Path, help="a results folder written by the pipeline")
    parser.add_argument(
        "--region",
        type=float,
        nargs=4,
        metavar=("X0", "Y0", "X1", "Y1"),
        help="world box in metres (default: 40 m square at mid-trajectory)",
    )
    parser.add_argument("--scan", type=int, help="draw this scan id alone (default: all scans)")
    parser.add_argument("--pixel", type=float, help="cell size in metres (default: region / 400)")
    parser.add_argument("--bev", action="store_true", help="draw the top-down map from map.npz")
    parser.add_argument("--out", type=Path, help="output PNG")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


@entry
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    require("matplotlib")
    try:
        if args.bev:
            return _bev(args.results_dir, args.out)
        from tisem.viz.compare import render_comparison

        result = render_comparison(
            args.results_dir, out=args.out, region=args.region, scan=args.scan, pixel_m=args.pixel
        )
    except (OSError, ValueError) as exc:  # DatasetError / MapFileError are ValueErrors
        print(f"render: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    x0, y0, x1, y1 = result["region"]
    print(
        f"wrote {result['out']}: region x {x0:.1f}..{x1:.1f} y {y0:.1f}..{y1:.1f} m, "
        f"{result['points']} points from {len(result['scans'])} scans"
    )
    for name, acc in result["accuracy"].items():
        print(f"  {name:8s} accuracy: " + ("n/a" if acc is None else f"{100 * acc:.2f} %"))
    share = 100 * result["changed"] / max(result["points"], 1)
    print(f"  map changed the network's label at {result['changed']} points ({share:.2f} %)")
    for line in result["skipped"]:
        print(f"  skipped scan {line}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
