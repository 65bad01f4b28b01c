"""The README's main table: the network input and every mode on the same scans.

    python benchmarks/modes.py                                  # mini KITTI data, 2 threads
    python benchmarks/modes.py --data DIR --sequence 08 --json modes.json

Each mode runs through the same pipeline as `apps/map_kitti.py` (final-map protocol, results in
`--out/<mode>/`) in a fresh Taichi runtime; seconds per scan is the median of the mapping step.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import KITTI_MINI, benchmark_main, device_line

MODES = ("csm", "bki", "spatial", "adaptive", "st")


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--data", type=Path, default=None, help="sequence folder (default: mini KITTI)")
    p.add_argument("--sequence", default=None)
    p.add_argument("--modes", nargs="+", default=list(MODES))
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--out", type=Path, default=Path("results/modes"))
    p.add_argument("--arch", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path)
    return p.parse_args(argv)


def run(args) -> dict:
    from tisem.backend import init_taichi
    from tisem.config import load_config
    from tisem.io.semantickitti import SemanticKittiSequence
    from tisem.pipeline import run_pipeline

    data = args.data or KITTI_MINI
    rows = []
    for mode in args.modes:
        cfg = load_config(None, [*args.overrides, f"mode={mode}"])
        seq = SemanticKittiSequence(data, sequence=args.sequence)
        init_taichi(args.arch, threads=args.threads)
        result = run_pipeline(
            seq,
            cfg,
            args.out / mode,
            sequence_name=seq.sequence_name,
            total=len(seq),
            progress=False,
            write_outputs=False,
            source_info={"data": str(data)},
        )
        m = result.metrics
        if not rows:
            rows.append({"row": "network input", **m["input"], "seconds_per_scan": None})
        rows.append({"row": mode, **m["final"], "seconds_per_scan": m["seconds_per_scan"]})
        logging.info(
            "%s: mIoU %.4f accuracy %.4f", mode, m["final"]["miou"], m["final"]["accuracy"]
        )
    return {"data": str(data), "device": device_line(args.arch), "rows": rows}


def format_rows(rows) -> str:
    out = [
        "| row | mIoU | accuracy | wIoU | OA (paper) | s / scan |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        sps = "–" if r["seconds_per_scan"] is None else f"{r['seconds_per_scan']:.3f}"
        out.append(
            f"| {r['row']} | {r['miou']:.4f} | {r['accuracy']:.4f} | {r['wiou']:.4f} | "
            f"{r['oa_paper']:.4f} | {sps} |"
        )
    return "\n".join(out)


def format_result(result: dict) -> str:
    return f"\ndata: {result['data']}\ndevice: {result['device']}\n\n" + format_rows(result["rows"])


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
