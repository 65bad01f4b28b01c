"""Map a SemanticKITTI sequence (or, given no data, a synthetic one) and score it.

    python apps/map_kitti.py --arch cpu                      # synthetic street, under a minute
    python apps/map_kitti.py --data ../shared/data/semantickitti_08_mini --sequence 08
    python apps/map_kitti.py --data /data/kitti/dataset --sequence 08 --first 0 --last 99
    python apps/map_kitti.py --data ... --out results/run --checkpoint-every 100   # then, after a crash:
    python apps/map_kitti.py --resume results/run
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from tisem import cli
from tisem.errors import DatasetError

log = logging.getLogger("map_kitti")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, help="a sequence folder, or a dataset root with --sequence "
                                             "(default: generate a synthetic sequence)")
    p.add_argument("--sequence", help="sequence name, e.g. 08")
    p.add_argument("--input", choices=("predictions", "labels"), default=None,
                   help="which label files feed the map (default predictions)")
    p.add_argument("--synthetic-scans", type=int, default=20, help="scans of the embedded default")
    p.add_argument("--seed", type=int, default=0, help="seed of the embedded default")
    g = p.add_argument_group("checkpoints")
    g.add_argument("--checkpoint-every", type=int, metavar="N",
                   help="save the map and the metrics so far every N mapped scans, atomically, "
                        "to <out>/checkpoint/ (default: never; a resumed run keeps its N)")
    g.add_argument("--resume", type=Path, metavar="DIR",
                   help="continue the run of results folder DIR (or its checkpoint folder) with "
                        "its stored config and data, in that folder unless --out is given; "
                        "--last may extend it")
    cli.add_common_args(p)
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    cli.setup_logging(args.verbose)
    from tisem.io.semantickitti import SemanticKittiSequence
    from tisem.pipeline import results_table, run_pipeline

    ckpt = None
    if args.resume is not None:
        from tisem.checkpoint import load_checkpoint
        if args.config or args.overrides or args.mode or args.input:
            log.error("--resume continues with the config stored in the checkpoint: drop "
                      "--config / --set / --mode / --input")
            return 2
        try:
            ckpt = load_checkpoint(args.resume)
            cfg = ckpt.run_config()
        except (KeyError, ValueError, OSError) as exc:
            log.error("resume: %s", exc)
            return 2
        if args.first is not None:
            cfg.first = args.first
        if args.last is not None:
            cfg.last = args.last
        if args.out is None:
            args.out = ckpt.results_dir
        source = ckpt.source
        if args.data is None and source.get("data") is None:
            log.error("resume: the checkpoint does not say where the data is; give --data")
            return 2
        args.data = args.data or Path(source["data"])
        args.sequence = args.sequence or source.get("sequence")
        if args.checkpoint_every is None:
            args.checkpoint_every = source.get("checkpoint_every")
        log.info("resuming %s after scan %s", ckpt.path, ckpt.last_index)
    else:
        try:
            cfg = cli.run_config_from_args(args)
        except (KeyError, ValueError, OSError) as exc:
            log.error("config: %s", exc)
            return 2
    if args.input:
        cfg.input = args.input
    try:   # first, so that a backend that cannot start costs nothing
        device = cli.init_backend(args)
    except cli.BackendError as exc:
        log.error("%s", exc)
        return 2
    out = cli.results_dir(args)
    data, sequence = args.data, args.sequence
    if data is None:
        from tisem.synth.sequence import write_semantickitti
        data = out / "synthetic"
        log.info("no --data: generating a synthetic street (%d scans, seed %d) in %s",
                 args.synthetic_scans, args.seed, data)
        write_semantickitti(data, args.synthetic_scans, seed=args.seed, progress=not args.no_progress)
    try:
        seq = SemanticKittiSequence(data, sequence=sequence, input=cfg.input, first=cfg.first,
                                    last=cfg.last)
    except DatasetError as exc:
        log.error("%s", exc)
        return 2
    log.info("%s: sequence %s, %d scans, mode %s, %s", seq.sequence_dir, seq.sequence_name,
             len(seq), cfg.mapper.mode, device)
    result = run_pipeline(seq, cfg, out, sequence_name=seq.sequence_name, total=len(seq),
                          progress=not args.no_progress,
                          source_info={"data": str(Path(seq.sequence_dir).resolve()),
                                       "first": cfg.first, "last": cfg.last,
                                       "scan_ids": list(map(int, seq.scan_ids)), "input": cfg.input,
                                       "arch": args.arch, "threads": args.threads,
                                       "checkpoint_every": args.checkpoint_every or 0},
                          checkpoint_every=args.checkpoint_every or 0, resume=ckpt)
    for s in result.skipped:
        log.warning("skipped scan %s: %s", s.index, s.reason)
    print(results_table(result.metrics))
    print(f"\nresults in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
