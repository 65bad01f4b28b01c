"""Per-stage milliseconds per scan, scans per second, memory, and the speedup over numpy.

    python benchmarks/throughput.py                      # mini KITTI data, 2 threads, st mode
    python benchmarks/throughput.py --scans 40 --mode bki --json out.json
    python benchmarks/throughput.py --arch cuda

Compile time (the first scan, which JIT-compiles every kernel) is reported apart from the
steady state. Every clock read is preceded by ti.sync(); figures are medians over the scans.

The steady state replays a few scans at one place: the map is revisited, not grown. A map that
is still growing pays for its new leaf blocks too, mostly in the operating system's page faults
on their first touch; `--fresh-maps R` also maps the distinct scans R times, each time into a
fresh map in a fresh runtime, and times every scan after the first (what benchmarks/peers.py
times). Both report the minor page faults per scan.
"""

from __future__ import annotations

import argparse
import resource
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
    p.add_argument(
        "--fresh-maps",
        type=int,
        default=0,
        metavar="R",
        help="also map the distinct scans R times into fresh maps, timing each scan after the "
        "first (0: skip)",
    )
    args = p.parse_args(argv)
    if args.fresh_maps < 0:
        p.error(f"--fresh-maps {args.fresh_maps}: expected a whole number >= 0")
    return args


def minor_faults() -> int:
    """The process's minor page faults so far (memory the OS maps in on first touch)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def timed_integrate(mapper, scan) -> tuple[float, int, dict[str, float]]:
    """(seconds, minor page faults, seconds per stage) of one `mapper.integrate(scan)`."""
    import taichi as ti

    before = dict(mapper.stage_seconds)
    ti.sync()
    faults = minor_faults()
    t0 = time.perf_counter()
    mapper.integrate(scan)
    ti.sync()
    seconds = time.perf_counter() - t0
    stages = {s: mapper.stage_seconds[s] - v for s, v in before.items()}
    return seconds, minor_faults() - faults, stages


def fresh_maps(args, cfg, scans) -> dict:
    """Each round maps `scans` into a fresh map in a fresh runtime; every scan after the first
    (which compiles or loads the kernels) is timed."""
    from tisem.backend import init_taichi
    from tisem.mapper import STAGES, Mapper

    per_stage = {s: [] for s in STAGES}
    total, faults = [], []
    for _ in range(args.fresh_maps):
        init_taichi(args.arch, threads=args.threads)
        mapper = Mapper(cfg, profile=True)
        for k, scan in enumerate(replay(scans, len(scans))):
            seconds, n_faults, stages = timed_integrate(mapper, scan)
            if k == 0:
                continue
            total.append(seconds)
            faults.append(n_faults)
            for s in STAGES:
                per_stage[s].append(stages[s])
    return {
        "rounds": args.fresh_maps,
        "distinct_scans": len(scans),
        "scans": len(total),
        "seconds_per_scan": median(total),
        "minor_faults_per_scan": median(faults),
        "stages": {s: 1000 * median(v) for s, v in per_stage.items()},
    }


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
    total, points, faults = [], [], []
    for scan in stream:
        seconds, n_faults, stages = timed_integrate(mapper, scan)
        t1 = time.perf_counter()
        mapper.query(scan.points_world(), with_probs=False)
        ti.sync()
        per_stage["query"].append(time.perf_counter() - t1)
        for s in STAGES:
            per_stage[s].append(stages[s])
        total.append(seconds)
        faults.append(n_faults)
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
        "minor_faults_per_scan": median(faults),
        "stages": {s: 1000 * median(v) for s, v in per_stage.items()},
        "peak_rss_mb": peak_rss_mb(),
        "active_voxels": mapper.live_voxels + mapper.stored_voxels,
    }
    if args.fresh_maps:  # (after the figures above: a fresh runtime ends this map)
        result["fresh_map"] = fresh_maps(args, cfg, scans)
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


def stage_table(part: dict) -> list[str]:
    """The median ms per scan of each stage and end to end of a result (or its fresh maps)."""
    lines = ["| stage | ms per scan (median) |", "| --- | ---: |"]
    lines += [f"| {s} | {v:.1f} |" for s, v in part["stages"].items()]
    lines.append(f"| **mapping, end to end** | **{1000 * part['seconds_per_scan']:.1f}** |")
    return lines


def format_result(r: dict) -> str:
    lines = [
        f"device: {r['device']}",
        f"data: {r['source']}, mode {r['mode']}, "
        f"{r['points_per_scan']:.0f} points per scan, {r['scans']} steady-state scans",
        "",
        *stage_table(r),
        "",
        f"scans per second: {r['scans_per_second']:.1f}; compile (first scan): "
        f"{r['compile_seconds']:.2f} s; peak RSS {r['peak_rss_mb']:.0f} MB; "
        f"{r['active_voxels']:,} voxels; {r['minor_faults_per_scan']:,.0f} page faults per scan",
    ]
    if "speedup_vs_numpy" in r:
        lines.append(
            f"numpy reference: {r['reference_seconds_per_scan']:.2f} s per scan -> "
            f"tisem is {r['speedup_vs_numpy']:.0f}x faster"
        )
    fresh = r.get("fresh_map")
    if fresh:
        lines += [
            "",
            f"fresh maps ({fresh['rounds']} rounds of the {fresh['distinct_scans']} distinct "
            f"scans, each scan after the first timed, {fresh['scans']} in all):",
            "",
            *stage_table(fresh),
            "",
            f"{fresh['minor_faults_per_scan']:,.0f} page faults per scan",
        ]
    return "\n".join(lines)


def main(argv=None) -> int:
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
