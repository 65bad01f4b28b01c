"""How fast MCAP recordings turn into scans: points per second through `McapScanReader`.

    python benchmarks/mcap_decode.py                       # 20 scans x 120k points, 3 codecs
    python benchmarks/mcap_decode.py --scans 50 --compression zstd --json results/decode.json

For each codec a synthetic ROS 2 log (`write_synthetic_log`: ring-structured 64-beam clouds,
x y z intensity float32 + uint16 label, /tf at 50 Hz, /tf_static) is written to a temporary
folder, then read `--runs` times. Columns (median over runs):
- records: the record layer alone (read, inflate, CRC-check every chunk);
- survey: the reader's first pass (records + /tf decode + topic/field checks);
- scans: the second pass (records + CDR decode + numpy views + tf lookup -> `Scan`);
- total and points/s: survey + scans, what `map_mcap.py` pays before mapping.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import benchmark_main


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--scans", type=int, default=20, help="clouds in the log (default 20)")
    p.add_argument("--points", type=int, default=120_000, help="points per cloud (default 120k)")
    p.add_argument(
        "--compression", nargs="+", choices=("zstd", "lz4", "none"), default=["zstd", "lz4", "none"]
    )
    p.add_argument("--runs", type=int, default=5, help="timed runs per codec (median)")
    p.add_argument("--json", type=Path, help="also write the results here")
    return p.parse_args(argv)


def _median_seconds(fn, runs: int) -> float:
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def run(args: argparse.Namespace) -> dict:
    from tisem.io.mcap_reader import McapScanReader
    from tisem.io.mcap_records import McapRecords, ReadReport
    from tisem.synth.mcap_log import write_synthetic_log

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for codec in args.compression:
            path = Path(tmp) / f"bench_{codec}.mcap"
            write_synthetic_log(path, n_scans=args.scans, n_points=args.points, compression=codec)
            reader = McapScanReader(path)  # warm-up (decoder generation)
            n_points = sum(s.num_points for s in reader)

            def records(path=path):
                for _ in McapRecords(path).records(ReadReport()):
                    pass

            t_records = _median_seconds(records, args.runs)
            t_survey = _median_seconds(lambda path=path: McapScanReader(path), args.runs)
            t_scans = _median_seconds(lambda reader=reader: sum(1 for _ in reader), args.runs)
            total = t_survey + t_scans
            rows.append(
                {
                    "compression": codec,
                    "scans": args.scans,
                    "points": n_points,
                    "file_mb": path.stat().st_size / 1e6,
                    "records_s": t_records,
                    "survey_s": t_survey,
                    "scans_s": t_scans,
                    "total_s": total,
                    "ms_per_scan": 1e3 * total / args.scans,
                    "points_per_s": n_points / total,
                }
            )
    return {
        "date": dt.date.today().isoformat(),
        "machine": _machine(),
        "runs": args.runs,
        "rows": rows,
    }


def _machine() -> str:
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    cpu = platform.processor() or platform.machine()
    return f"{cpu}, {cpus} cores, Python {platform.python_version()}"


def table(result: dict) -> str:
    head = (
        "| codec | scans x points | file MB | records s | survey s | scans s | ms / scan | "
        "M points/s |\n| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |\n"
    )
    return head + "\n".join(
        f"| {r['compression']} | {r['scans']} x {r['points'] // r['scans']:,} | "
        f"{r['file_mb']:.1f} | {r['records_s']:.3f} | {r['survey_s']:.3f} | {r['scans_s']:.3f} | "
        f"{r['ms_per_scan']:.1f} | "
        f"{r['points_per_s'] / 1e6:.1f} |"
        for r in result["rows"]
    )


def format_result(result: dict) -> str:
    return (
        f"MCAP decode, {result['date']}, {result['machine']}, "
        f"median of {result['runs']} runs\n\n" + table(result)
    )


def main(argv: list[str] | None = None) -> int:
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
