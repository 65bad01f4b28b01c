"""Run sequences x configs as Ray tasks; one table (and batch.json) of every cell's metrics.

    tisem batch /data/kitti/dataset --sweep mode=bki,st --out results/sweep
    tisem batch data/robots --sweep tau_s=1,2,5,10 --sweep ell_max_m=0.8,1.2
    tisem batch ... --out results/sweep          # again: only what is missing runs
    tisem batch drive.db3 --gt-field gt_label --sweep tau_s=1,5   # a recording, scored

LOG: a SemanticKITTI dataset root or sequence folder, or a recording (an .mcap, .db3 or ROS 1
.bag file, a rosbag2 folder), read with the recording options (those of `tisem map-mcap`).
A cell is one log under one config (--set / --config, then one value of every --sweep); it
is a mapping run in its own process into <out>/<log>/<cell>/. Finished cells are kept.
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

log = logging.getLogger("tisem.batch")


def build_parser() -> argparse.ArgumentParser:
    p = new_parser("batch", __doc__)
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
    p.add_argument(
        "--sweep",
        action="append",
        default=[],
        metavar="KEY=V1,V2,...",
        help="run every value of a config key (repeatable: the product)",
    )
    p.add_argument("--no-map-files", action="store_true", help="no map.npz / ply / png per cell")
    add_cluster_args(p)
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def batch(args: argparse.Namespace) -> int:
    from tisem.batch import BatchOptions, batch_table, run_batch
    from tisem.logs import discover_logs

    overrides = list(args.overrides) + ([f"mode={args.mode}"] if args.mode else [])
    with cli.bad_input("options: "):
        recording = recording_options(args)
    with cli.bad_input():
        logs = discover_logs([p.resolve() for p in args.logs], args.sequences, recording)
        options = BatchOptions(
            threads=args.threads or 2,
            retries=args.retries,
            address=args.address,
            num_cpus=args.num_cpus,
            arch=args.arch,
            map_files=not args.no_map_files,
            progress=not args.no_progress,
        )
        out = results_folder(args.out)
        result = run_batch(
            logs,
            out,
            overrides=overrides,
            sweeps=args.sweep,
            options=options,
            config_path=args.config,
        )
    print(batch_table(result.rows))
    for row in result.rows:
        for line in row.get("read_losses") or ():
            print(f"{row['log']} ({row['cell']}): {line}")
    print(
        f"\n{result.ran} cells ran, {result.kept} kept, {len(result.failed)} failed; "
        f"batch.json in {result.out_dir}"
    )
    return 1 if result.failed else 0


@entry
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    require("ray")  # --help works without the extra
    return cli.run_app(batch, args, log)


if __name__ == "__main__":
    sys.exit(main())
