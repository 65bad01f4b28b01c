"""Per-stage milliseconds per scan, scans per second, memory, and the speedup over numpy.

    python benchmarks/throughput.py                      # mini KITTI data, 2 threads, st mode
    python benchmarks/throughput.py --scans 40 --mode bki --json out.json
    python benchmarks/throughput.py --arch cuda

Compile time (the first scan, which JIT-compiles every kernel) is reported apart from the
steady state. Every clock read is preceded by ti.sync(); figures are medians over the scans.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (
    add_data_args,
    benchmark_main,
    device_line,
    load_scans,
    median,
    peak_rss_mb,
    replay,
)


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_data_args(p)
    p.add_argument("--scans", type=int, default=30, help="steady-state scans to time")
    p.add_argument("--mode", default="st")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument(
        "--reference-scans",
        type=int,
        default=2,
        help="scans to run through the numpy reference for the speedup (0: skip)",
    )
    return p.parse_args(argv)


def run(args) -> dict:
    import taichi as ti

    from tisem.backend import init_taichi
    from tisem.config import load_config
    from tisem.mapper import STAGES, Mapper

    cfg = load_config(None, [f"mode={args.mode}", *args.overrides]).mapper
    scans, source = load_scans(args, 5)
    init_taichi(args.arch, threads=args.threads)
    mapper = Mapper(cfg, profile=True)

    stream = replay(scans, args.scans + 1)
    first = next(stream)
    ti.sync()
    t0 = time.perf_counter()
    mapper.integrate(first)
    mapper.query(first.points_world(), with_probs=False)
    ti.sync()
    compile_s = time.perf_counter() - t0

    per_stage = {s: [] for s in (*STAGES, "query")}
    total = []
    points = []
    for scan in stream:
        before = dict(mapper.stage_seconds)
        ti.sync()
        t0 = time.perf_counter()
        mapper.integrate(scan)
        ti.sync()
        t1 = time.perf_counter()
        mapper.query(scan.points_world(), with_probs=False)
        ti.sync()
        t2 = time.perf_counter()
        for s in STAGES:
            per_stage[s].append(mapper.stage_seconds[s] - before[s])
        per_stage["query"].append(t2 - t1)
        total.append(t1 - t0)
        points.append(scan.num_points)

    result = {
        "source": source,
        "device": device_line(args.arch),
        "arch": args.arch,
        "threads": args.threads,
        "mode": cfg.mode,
        "config": vars(cfg),
        "scans": len(total),
        "points_per_scan": median(points),
        "compile_seconds": compile_s,
        "seconds_per_scan": median(total),
        "scans_per_second": 1.0 / median(total),
        "stages": {s: 1000 * median(v) for s, v in per_stage.items()},
        "peak_rss_mb": peak_rss_mb(),
        "active_voxels": mapper.live_voxels + mapper.stored_voxels,
    }
    if args.reference_scans:
        from tisem.reference import ReferenceMapper

        ref = ReferenceMapper(cfg)
        ref_times = []
        for scan in replay(scans, args.reference_scans + 1):
            t0 = time.perf_counter()
            ref.integrate(scan)
            ref_times.append(time.perf_counter() - t0)
        # the first reference scan builds a fresh map, like the first timed Taichi scan did not;
        # compare steady states: reference scans after its first
        result["reference_seconds_per_scan"] = median(ref_times[1:])
        result["speedup_vs_numpy"] = (
            result["reference_seconds_per_scan"] / result["seconds_per_scan"]
        )
    return result


def format_result(r: dict) -> str:
    lines = [
        f"device: {r['device']}",
        f"data: {r['source']}, mode {r['mode']}, "
        f"{r['points_per_scan']:.0f} points per scan, {r['scans']} steady-state scans",
        "",
        "| stage | ms per scan (median) |",
        "| --- | ---: |",
    ]
    lines += [f"| {s} | {v:.1f} |" for s, v in r["stages"].items()]
    lines += [
        f"| **mapping, end to end** | **{1000 * r['seconds_per_scan']:.1f}** |",
        "",
        f"scans per second: {r['scans_per_second']:.1f}; compile (first scan): "
        f"{r['compile_seconds']:.2f} s; peak RSS {r['peak_rss_mb']:.0f} MB; "
        f"{r['active_voxels']:,} voxels",
    ]
    if "speedup_vs_numpy" in r:
        lines.append(
            f"numpy reference: {r['reference_seconds_per_scan']:.2f} s per scan -> "
            f"tisem is {r['speedup_vs_numpy']:.0f}x faster"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
