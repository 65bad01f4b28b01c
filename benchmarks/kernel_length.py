"""The paper's Table I: fixed kernel lengths of 1, 2, 4, 6 voxels against the adaptive length.

    python benchmarks/kernel_length.py              # mini KITTI data and a synthetic street
    python benchmarks/kernel_length.py --data DIR --scans 10 --json table1.json

Every row maps the same scans with plain accumulation (modes `bki` and `adaptive`, so the only
difference is the kernel length) in a fresh Taichi runtime; the first scan, which compiles the
kernels, is timed apart. The kernels take turns over `--repeats` rounds and the times are
medians over all of them, so a drift in the machine's speed does not favour one row. Accuracy
and mIoU follow the final-map protocol (every ground-truth point of every scan looked up in the
map after the last scan). The `st` row (adaptive + decay, the default) is added for reference.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import KITTI_MINI, benchmark_main, device_line, median

FIXED_VOXELS = (1, 2, 4, 6)


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--data",
        type=Path,
        default=None,
        help="SemanticKITTI sequence folder (default: the mini KITTI data when present)",
    )
    p.add_argument(
        "--synthetic-scans",
        type=int,
        default=20,
        help="also run a synthetic street of this many scans (0: skip)",
    )
    p.add_argument("--scans", type=int, default=None, help="use at most this many scans of --data")
    p.add_argument("--arch", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="rounds in which every kernel maps the scans once, taking turns",
    )
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--json", type=Path, help="write the rows as JSON here")
    return p.parse_args(argv)


def map_once(scans, cfg, args):
    """Map the scans in a fresh runtime: (seconds per scan, the first compiling; final metrics)."""
    import taichi as ti

    from tisem.backend import init_taichi
    from tisem.evaluate import Confusion
    from tisem.mapper import Mapper

    init_taichi(args.arch, threads=args.threads)
    mapper = Mapper(cfg)
    seconds = []
    for scan in scans:
        ti.sync()
        t0 = time.perf_counter()
        mapper.integrate(scan)
        ti.sync()
        seconds.append(time.perf_counter() - t0)
    conf = Confusion(mapper.C)
    for scan in scans:
        labels, _ = mapper.query(scan.points_world(), with_probs=False)
        conf.add(scan.gt_labels, labels)
    return seconds, conf.metrics()


def rows_for(scans, label: str, args) -> list[dict]:
    """One row per kernel. The kernels take turns, `--repeats` rounds of each, so that a machine
    whose speed drifts over minutes slows every kernel alike; times are medians over all rounds."""
    from tisem.config import load_config

    settings = [(f"fixed {v} vox", ["mode=bki", f"ell_fixed_vox={v}"]) for v in FIXED_VOXELS]
    settings += [("adaptive", ["mode=adaptive"]), ("adaptive + decay (st)", ["mode=st"])]
    configs = [load_config(None, [*args.overrides, *sets]).mapper for _, sets in settings]
    steady = [[] for _ in settings]  # per kernel: steady-state seconds of every round
    totals = [[] for _ in settings]  # per kernel: seconds for the N steady scans, per round
    compile_s = [[] for _ in settings]
    metrics = [None] * len(settings)
    for rnd in range(args.repeats):
        for k, ((name, _), cfg) in enumerate(zip(settings, configs)):
            seconds, metrics[k] = map_once(scans, cfg, args)
            rest = seconds[1:] if len(seconds) > 1 else seconds
            steady[k] += rest
            totals[k].append(float(np.sum(rest)))
            compile_s[k].append(seconds[0] - median(rest))
            print(
                f"  {label} (round {rnd + 1}/{args.repeats}): {name:>22}  "
                f"{1000 * median(rest):7.1f} ms/scan  acc {metrics[k]['accuracy']:.4f}  "
                f"mIoU {metrics[k]['miou']:.4f}",
                flush=True,
            )
    rows = []
    for k, ((name, _), cfg) in enumerate(zip(settings, configs)):
        length = (
            f"{cfg.ell_fixed_vox * cfg.resolution_m:.1f} m"
            if cfg.mode == "bki"
            else f"{cfg.ell_min_m:.1f}-{cfg.ell_max_m:.1f} m"
        )
        rows.append(
            {
                "data": label,
                "kernel": name,
                "length": length,
                "seconds_per_scan": median(steady[k]),
                "seconds_total": median(totals[k]),
                "compile_seconds": median(compile_s[k]),
                "scans": len(scans),
                "rounds": args.repeats,
                "accuracy": metrics[k]["accuracy"],
                "miou": metrics[k]["miou"],
            }
        )
    return rows


def format_rows(rows: list[dict]) -> str:
    out = [
        "| data | kernel | length | s / scan | s for N scans (N) | accuracy | mIoU |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        out.append(
            f"| {r['data']} | {r['kernel']} | {r['length']} | {r['seconds_per_scan']:.3f} | "
            f"{r['seconds_total']:.2f} ({r['scans'] - 1}) | {r['accuracy']:.4f} | "
            f"{r['miou']:.4f} |"
        )
    return "\n".join(out)


def run(args) -> dict:
    from tisem.io.semantickitti import SemanticKittiSequence
    from tisem.scan import Scan

    rows = []
    data = args.data if args.data is not None else (KITTI_MINI if KITTI_MINI.is_dir() else None)
    if data is not None:
        seq = SemanticKittiSequence(data, last=None if args.scans is None else args.scans - 1)
        scans = [s for s in seq if isinstance(s, Scan)]
        rows += rows_for(scans, f"{data.name}", args)
    if args.synthetic_scans:
        from tisem.synth.sequence import iter_synthetic, to_scan

        scans = [to_scan(f) for f in iter_synthetic(args.synthetic_scans, seed=0)]
        rows += rows_for(scans, f"synthetic street ({args.synthetic_scans})", args)
    return {
        "device": device_line(args.arch),
        "arch": args.arch,
        "threads": args.threads,
        "rows": rows,
    }


def format_result(result: dict) -> str:
    return f"\ndevice: {result['device']}\n\n" + format_rows(result["rows"])


def main(argv=None) -> int:
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
