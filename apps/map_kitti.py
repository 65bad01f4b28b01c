"""Map a SemanticKITTI sequence (or, given no data, a synthetic one) and score it.

    python apps/map_kitti.py --arch cpu                      # synthetic street, under a minute
    python apps/map_kitti.py --data ../shared/data/semantickitti_08_mini --sequence 08
    python apps/map_kitti.py --data /data/kitti/dataset --sequence 08 --first 0 --last 99
    python apps/map_kitti.py --data ... --out results/run --checkpoint-every 100
    python apps/map_kitti.py --resume results/run            # after a crash: go on
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from tisem import cli

log = logging.getLogger("map_kitti")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, help="a sequence folder, or a dataset root with --sequence "
                                             "(default: generate a synthetic sequence)")
    p.add_argument("--sequence", help="sequence name, e.g. 08")
    p.add_argument("--input", choices=("predictions", "labels"), default=None,
                   help="which label files feed the map (default predictions)")
    p.add_argument("--synthetic-scans", type=int, default=20, help="scans of the embedded default")
    p.add_argument("--seed", type=int, default=0, help="seed of the embedded default")
    cli.add_run_args(p)
    return cli.parse_run_args(p, argv, kept_on_resume={"input": "--input"})


def open_sequence(data: Path, sequence: str | None, cfg):
    from tisem.io.semantickitti import SemanticKittiSequence
    with cli.bad_input():
        return SemanticKittiSequence(data, sequence=sequence, input=cfg.input, first=cfg.first,
                                     last=cfg.last)


def map_sequence(args: argparse.Namespace) -> int:
    from tisem.labels import NUM_CLASSES
    from tisem.report import results_table

    plan = cli.plan_run(args)
    cfg = plan.cfg
    if args.input:
        cfg.input = args.input
    if cfg.mapper.num_classes < NUM_CLASSES:
        raise cli.AppError(f"config: num_classes = {cfg.mapper.num_classes}: SemanticKITTI "
                           f"labels are train ids 0..{NUM_CLASSES - 1}; expected >= "
                           f"{NUM_CLASSES}")
    data = plan.input_path(args.data, "data", "--data")
    sequence = args.sequence or plan.source.get("sequence")
    # the input is opened before anything is made: a bad one leaves no results folder
    seq = open_sequence(data, sequence, cfg) if data is not None else None
    plan.start(args)
    if seq is None:
        from tisem.synth.sequence import write_semantickitti
        data = plan.out_dir / "synthetic"
        log.info("no --data: generating a synthetic street (%d scans, seed %d) in %s",
                 args.synthetic_scans, args.seed, data)
        write_semantickitti(data, args.synthetic_scans, seed=args.seed,
                            progress=not args.no_progress)
        seq = open_sequence(data, sequence, cfg)
    log.info("%s: sequence %s, %d scans, mode %s, %s", seq.sequence_dir, seq.sequence_name,
             len(seq), cfg.mapper.mode, plan.device)
    source_info = {"data": str(Path(seq.sequence_dir).resolve()), "first": cfg.first,
                   "last": cfg.last, "scan_ids": list(map(int, seq.scan_ids)),
                   "input": cfg.input, "arch": args.arch, "threads": plan.threads}
    run = plan.mapping_run(seq, args, sequence_name=seq.sequence_name, total=len(seq),
                           source_info=source_info)
    result = run.run(show_progress=not args.no_progress)
    print(results_table(result.metrics))
    print(f"\nresults in {plan.out_dir}")
    return plan.finish(result)


def main(argv: list[str] | None = None) -> int:
    return cli.run_app(map_sequence, parse_args(argv), log)


if __name__ == "__main__":
    sys.exit(main())
