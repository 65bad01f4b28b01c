"""Map a SemanticKITTI sequence (or, given no data, a synthetic one) and score it.

tisem map-kitti --arch cpu                      # synthetic street, under a minute
tisem map-kitti --data path/to/semantickitti_08_mini --sequence 08
tisem map-kitti --data /data/kitti/dataset --sequence 08 --first 0 --last 99
tisem map-kitti --data my_drive/ --poses kiss_icp_poses.txt --classes my_classes.yaml
tisem map-kitti --data /data/kitti/dataset --sequence 08 --predictions runs/cylinder3d
tisem map-kitti --data ... --out results/run --checkpoint-every 100
tisem map-kitti --resume results/run            # after a crash: go on
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from tisem import cli
from tisem.commands import entry, new_parser

if TYPE_CHECKING:  # (imported when needed: the help stays fast)
    from tisem.config import RunConfig
    from tisem.io.semantickitti import SemanticKittiSequence

log = logging.getLogger("tisem.map_kitti")
KEPT_ON_RESUME = {
    "input": "--input",
    "poses": "--poses",
    "predictions": "--predictions",
    "label_space": "--label-space",
}


def build_parser() -> argparse.ArgumentParser:
    p = new_parser("map_kitti", __doc__)
    p.add_argument(
        "--data",
        type=Path,
        help="a sequence folder, or a dataset root with --sequence "
        "(default: generate a synthetic sequence)",
    )
    p.add_argument("--sequence", help="sequence name under a dataset root, e.g. 08")
    p.add_argument(
        "--input",
        choices=("predictions", "labels"),
        default=None,
        help="which label files feed the map: the network's predictions/ or the "
        "ground truth labels/ (default predictions)",
    )
    p.add_argument(
        "--poses",
        type=Path,
        metavar="FILE",
        help="LiDAR-frame trajectory, one pose per scan, KITTI (3x4 rows) or TUM "
        "(t x y z qx qy qz qw) format, e.g. a KISS-ICP result (default: the "
        "sequence's poses.txt or dataset/poses/NN.txt with calib.txt's Tr)",
    )
    p.add_argument(
        "--predictions",
        type=Path,
        metavar="DIR",
        help="the network's label files, when not the sequence's predictions/: a folder of "
        "NNNNNN.label, or the root a semantic-kitti-api style run writes "
        "(DIR/sequences/NN/predictions/)",
    )
    p.add_argument(
        "--label-space",
        choices=("auto", "raw", "train"),
        default=None,
        help="the label files hold raw SemanticKITTI ids, train ids 0..19, or either (auto, "
        "the default: told apart per file, each said once in a warning)",
    )
    p.add_argument(
        "--synthetic-scans",
        type=int,
        default=20,
        help="scans of the synthetic street mapped when no --data is given",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic street")
    cli.add_run_args(p)
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return cli.parse_run_args(build_parser(), argv, kept_on_resume=KEPT_ON_RESUME)


def open_sequence(
    data: Path,
    sequence: str | None,
    cfg: RunConfig,
    poses: Path | None = None,
    predictions: Path | None = None,
    label_space: str = "auto",
) -> SemanticKittiSequence:
    from tisem.io.semantickitti import SemanticKittiSequence

    with cli.bad_input():
        return SemanticKittiSequence(
            data,
            sequence=sequence,
            input=cfg.input,
            first=cfg.first,
            last=cfg.last,
            poses=poses,
            predictions=predictions,
            label_space=label_space,
        )


def cache_root() -> Path:
    """Where tisem keeps what it can make again: $TISEM_CACHE_DIR, else $XDG_CACHE_HOME/tisem,
    else ~/.cache/tisem."""
    if os.environ.get("TISEM_CACHE_DIR"):
        return Path(os.environ["TISEM_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "tisem"


def synthetic_street(scans: int, seed: int, progress: bool) -> Path:
    """The synthetic street of the demo run, written once per (scans, seed, tisem version) into
    the cache and reused after (it is tens of MB). It is written to a temporary folder and
    renamed when complete, so an interrupted write is never mistaken for a street."""
    from tisem import __version__
    from tisem.synth.sequence import write_semantickitti

    folder = cache_root() / f"synthetic-street-{scans}scans-seed{seed}-v{__version__}"
    if folder.is_dir():
        log.info("no --data: the synthetic street (%d scans, seed %d) from %s", scans, seed, folder)
        return folder
    log.info(
        "no --data: generating a synthetic street (%d scans, seed %d) in %s", scans, seed, folder
    )
    partial = folder.with_name(f"{folder.name}.partial-{os.getpid()}")
    shutil.rmtree(partial, ignore_errors=True)
    write_semantickitti(partial, scans, seed=seed, progress=progress)
    try:
        os.rename(partial, folder)
    except OSError:  # another run finished the same street first
        shutil.rmtree(partial, ignore_errors=True)
    return folder


def map_sequence(args: argparse.Namespace) -> int:
    from tisem.labels import num_classes
    from tisem.report import results_table

    plan = cli.plan_run(args)
    cfg = plan.cfg
    if args.input:
        cfg.input = args.input
    if cfg.mapper.num_classes < num_classes():
        raise cli.AppError(
            f"config: num_classes = {cfg.mapper.num_classes}: the labels are "
            f"train ids 0..{num_classes() - 1}; expected >= {num_classes()}, "
            f"or --classes YAML for another label space"
        )
    data = plan.input_path(args.data, "data", "--data")
    sequence = args.sequence or plan.source.get("sequence")
    poses = args.poses or (Path(plan.source["poses"]) if plan.source.get("poses") else None)
    predictions = args.predictions or (
        Path(plan.source["predictions"]) if plan.source.get("predictions") else None
    )
    if predictions is not None and (cfg.input == "labels" or data is None):
        raise cli.AppError(
            f"--predictions {predictions}: "
            + (
                "the map is fed the ground truth (--input labels), not predictions"
                if cfg.input == "labels"
                else "give the sequence they belong to with --data"
            )
        )
    label_space = args.label_space or plan.source.get("label_space") or "auto"
    # the input is opened before anything is made: a bad one leaves no results folder
    seq = (
        open_sequence(data, sequence, cfg, poses, predictions, label_space)
        if data is not None
        else None
    )
    plan.start(args)
    if seq is None:
        with cli.bad_input("synthetic street: "):
            data = synthetic_street(args.synthetic_scans, args.seed, not args.no_progress)
        seq = open_sequence(data, sequence, cfg, label_space=label_space)
    log.info(
        "%s: sequence %s, %d scans, mode %s, %s",
        seq.sequence_dir,
        seq.sequence_name,
        len(seq),
        cfg.mapper.mode,
        plan.device,
    )
    source_info = {
        "data": str(Path(seq.sequence_dir).resolve()),
        "first": cfg.first,
        "last": cfg.last,
        "scan_ids": list(map(int, seq.scan_ids)),
        "input": cfg.input,
        "arch": args.arch,
        "threads": plan.threads,
        "poses": str(poses.resolve()) if poses else None,
        "predictions": str(seq.predictions_dir.resolve()) if predictions else None,
        "label_space": label_space,
        "classes": str(plan.classes) if plan.classes else None,
    }
    run = plan.mapping_run(
        seq, args, sequence_name=seq.sequence_name, total=len(seq), source_info=source_info
    )
    result = run.run(show_progress=not args.no_progress)
    input_name = "labels (input)" if cfg.input == "labels" else "network input"
    print(results_table(result.metrics, per_class=args.per_class, input_name=input_name))
    print(f"\nresults in {plan.out_dir}")
    return plan.finish(result)


@entry
def main(argv: list[str] | None = None) -> int:
    return cli.run_app(map_sequence, parse_args(argv), log)


if __name__ == "__main__":
    sys.exit(main())
