"""Where the free-space stage's time goes, and how much work its rays do per scan.

    python benchmarks/free_space.py                  # mini KITTI data, 2 threads, st mode
    python benchmarks/free_space.py --scans 60 --json out.json

The scans are replayed at 10 Hz as in benchmarks/throughput.py, with free space on. First run:
the stage's kernels, each call timed between ti.sync()s, a scan's calls summed (the rays to
the movers' points are a second `cast_free`), as median milliseconds per scan (the memory's
forget pass runs every quarter of seen_empty_s: its median over the scans that run it).
Second run, in a fresh runtime: per scan the rays, the voxels they cross (steps), the
steps in live leaf blocks and in live voxels, the steps that change the memory of space seen
empty (first crossings in the scan of space the map holds no voxel in) and the memory's new
blocks, counted by a kernel that walks the same rays (kernels/raycast.py `traverse`) just
before the scan's own pass, writing the memory as that pass would.
"""

import argparse
import sys
import time
from pathlib import Path

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from benchmarks.common import add_data_args, benchmark_main, device_line, load_scans, replay

KERNELS = ("flag_dynamic", "mark_hits", "cast_free", "clear_crossed", "forget_expired_blocks")
COUNTS = ("rays", "steps", "steps_live_blocks", "steps_live_voxels", "memory_writes")


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_data_args(p)
    p.add_argument("--scans", type=int, default=30, help="steady-state scans to time")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    return p.parse_args(argv)


def _timed(times: dict, name: str, kernel):
    import taichi as ti

    def call(*args):
        ti.sync()
        t0 = time.perf_counter()
        out = kernel(*args)
        ti.sync()
        times[name].append(time.perf_counter() - t0)
        return out

    return call


def time_kernels(args, cfg, scans) -> dict:
    """Median milliseconds per call of each kernel of the stage (after a compiling scan)."""
    from tisem.kernels import raycast, seen_empty

    from tisem.backend import init_taichi
    from tisem.mapper import Mapper

    init_taichi(args.arch, threads=args.threads)
    mapper = Mapper(cfg)
    free = mapper._free
    times = {k: [] for k in KERNELS}
    stream = replay(scans, args.scans + 1)
    mapper.integrate(next(stream))
    # (patched on the objects the mapper calls them through, and put back after)
    saved = raycast.flag_dynamic, seen_empty.forget_expired_blocks
    raycast.flag_dynamic = _timed(times, "flag_dynamic", saved[0])
    seen_empty.forget_expired_blocks = _timed(times, "forget_expired_blocks", saved[1])
    free._mark_hits = _timed(times, "mark_hits", free._mark_hits)
    free._cast_free = _timed(times, "cast_free", free._cast_free)
    free._clear_crossed = _timed(times, "clear_crossed", free._clear_crossed)
    per_scan = {k: [] for k in KERNELS}
    try:
        for scan in stream:
            calls = {k: len(v) for k, v in times.items()}
            mapper.integrate(scan)
            for k, v in times.items():
                if len(v) > calls[k]:  # (a scan's calls summed: the movers' rays are a second)
                    per_scan[k].append(sum(v[calls[k] :]))
    finally:
        raycast.flag_dynamic, seen_empty.forget_expired_blocks = saved
    return {k: 1000 * float(np.median(v)) if v else 0.0 for k, v in per_scan.items()}


def count_work(args, cfg, scans) -> dict:
    """Median per scan of the rays' work (COUNTS, and the memory's new blocks)."""
    import taichi as ti
    from tisem.kernels.layout import LEAF_BITS
    from tisem.kernels.params import ScanParams
    from tisem.kernels.raycast import free_fraction, traverse

    from tisem.backend import init_taichi
    from tisem.mapper import Mapper

    init_taichi(args.arch, threads=args.threads)
    mapper = Mapper(cfg)
    free = mapper._free
    tally = ti.field(ti.i64, shape=len(COUNTS))

    @ti.func
    def count_voxel(m: ti.template(), s: ti.template(), r, v):
        u = m.wrap(v)
        tally[1] += 1
        if ti.is_active(m.blk, u >> LEAF_BITS):  # (u's leaf block)
            tally[2] += 1
        if ti.is_active(m.vox, u):
            tally[3] += 1
        elif ti.static(m.seen_empty_s > 0):
            until = s.time_rel_s + m.seen_empty_s
            if m.empty_until[u] != until:
                m.empty_until[u] = until
                tally[4] += 1

    @ti.kernel
    def count_rays(
        m: ti.template(),
        s: ScanParams,
        xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),
        n_rows: ti.i32,
        stride: ti.i32,
        margin_m: ti.f32,
        margin_fraction: ti.f32,
    ):
        o = s.translation_m
        for q in range((n_rows + stride - 1) // stride):
            r = q * stride
            e = ti.Vector([xyz[r, 0], xyz[r, 1], xyz[r, 2]])
            t_stop = free_fraction((e - o).norm(), margin_m, margin_fraction)
            tally[0] += 1
            traverse(o * s.inv_resolution, e * s.inv_resolution, t_stop, count_voxel, m, s, r)

    @ti.kernel
    def memory_blocks(m: ti.template()) -> ti.i32:
        n = 0
        if ti.static(m.seen_empty_s > 0):
            for _ in ti.grouped(m.seen_blk):
                n += 1
        return n

    rows_of_scan = []
    new_blocks = 0
    cast = free._cast_free

    def counted_cast(m, s, xyz, n_rows, stride, margin_m, margin_fraction):
        nonlocal new_blocks
        before = memory_blocks(m)
        count_rays(m, s, xyz, n_rows, stride, margin_m, margin_fraction)
        new_blocks += memory_blocks(m) - before
        return cast(m, s, xyz, n_rows, stride, margin_m, margin_fraction)

    free._cast_free = counted_cast
    for scan in replay(scans, args.scans + 1):
        tally.fill(0)  # (summed over the scan's casts: the movers' rays are a second)
        new_blocks = 0
        mapper.integrate(scan)
        rows_of_scan.append([*tally.to_numpy(), new_blocks])
    per_scan = np.median(np.array(rows_of_scan[1:], dtype=np.float64), axis=0)
    return dict(zip((*COUNTS, "new_memory_blocks"), (float(x) for x in per_scan)))


def run(args) -> dict:
    from tisem.config import load_config

    cfg = load_config(None, ["mode=st", "free_space=true", *args.overrides]).mapper
    scans, source = load_scans(args, 5)
    kernels_ms = time_kernels(args, cfg, scans)
    counts = count_work(args, cfg, scans)
    return {
        "source": source,
        "device": device_line(args.arch),
        "threads": args.threads,
        "scans": args.scans,
        "config": vars(cfg),
        "kernels_ms": kernels_ms,
        "per_scan": counts,
    }


def format_result(r: dict) -> str:
    lines = [
        f"device: {r['device']}",
        f"data: {r['source']}, {r['scans']} steady-state scans, free space on",
        "",
        "| kernel | ms per scan (median) |",
        "| --- | ---: |",
    ]
    lines += [f"| {k} | {v:.2f} |" for k, v in r["kernels_ms"].items()]
    lines += ["", "| per scan (median) | |", "| --- | ---: |"]
    lines += [f"| {k} | {v:,.0f} |" for k, v in r["per_scan"].items()]
    return "\n".join(lines)


def main(argv=None) -> int:
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
