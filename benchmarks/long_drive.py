"""A whole drive at flat memory: a long synthetic loop, streamed scan by scan, with its revisit.

    python benchmarks/long_drive.py --scans 4000 --every 100 --json results/long_drive.json \
        --png docs/long_drive.png
    python benchmarks/long_drive.py --scans 300 --every 50           # a quick look
    python benchmarks/long_drive.py --probe-chunk            # where the 2nd GiB chunk comes

The drive is `tisem.synth.sequence`'s loop (4,000 scans = 3.9 km; scan 3,900 has the pose of
scan 0). Every `--every` scans it records the resident memory, the milliseconds per scan (median
of the last `--every`, `ti.sync()` around each `integrate`), and the live and stored voxels.

Loop closure: the ground-truth points of the first `--start-scans` scans are looked up in the map
three times: right after those scans, when the sensor has left the area for good (its voxels are
in the store by then) and after the last scan (the sensor has come back over them). The labels
must be the ones the area had, refined by the new scans, not lost: the benchmark reports the
accuracy against ground truth each time and the fraction of the area's voxels whose label changed.

`--probe-chunk` measures the cap instead: it maps the loop with a window that holds all of it and
no cap, watching the process's mappings, and stops as soon as taichi maps a second 1 GiB host
chunk (taichi 1.7.4's CPU allocator can overrun its first 1 GiB host chunk once it needs a second
one, which corrupts memory or crashes); it reports the live leaf blocks at that moment.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import benchmark_main, gib_mappings, peak_rss_mb, rss_mb, vms_mb


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--scans", type=int, default=4000, help="length of the drive (4000: the full loop)"
    )
    p.add_argument("--every", type=int, default=100, help="record a row every K scans")
    p.add_argument("--json", type=Path, help="write the results as JSON here")
    p.add_argument("--png", type=Path, help="draw memory, time and voxels over the drive here")
    p.add_argument("--arch", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--mode", default="st")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--points-per-ring",
        type=int,
        default=1024,
        help="azimuth samples per beam (1024: ~63k points per scan; 512 halves that)",
    )
    p.add_argument(
        "--start-scans",
        type=int,
        default=10,
        help="the scans whose ground truth defines the start area",
    )
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="mapper config override, e.g. --set window_xy_m=150",
    )
    p.add_argument(
        "--probe-chunk",
        action="store_true",
        help="find the live blocks at which taichi maps a second 1 GiB chunk",
    )
    p.add_argument(
        "--probe-window",
        type=float,
        default=1000.0,
        help="window half-size (m) for --probe-chunk: big enough to evict nothing",
    )
    return p.parse_args(argv)


# --------------------------------------------------------------------------- the drive


class StartArea:
    """The ground truth of the first scans, looked up in the map whenever asked."""

    def __init__(self, res: float):
        self.res = res
        self.points: list[np.ndarray] = []
        self.gt: list[np.ndarray] = []
        self.poses: list[np.ndarray] = []
        self.looks: dict[str, dict] = {}

    def add(self, scan) -> None:
        self.points.append(scan.points_world())
        self.gt.append(scan.gt_labels)
        self.poses.append(scan.T_world_sensor[:3, 3])

    def finish(self) -> None:
        self.points = np.concatenate(self.points)
        self.gt = np.concatenate(self.gt)
        self.poses = np.array(self.poses)
        keys = np.unique(np.floor(self.points / self.res).astype(np.int64), axis=0)
        self.centres = (keys + 0.5) * self.res  # one query per voxel the area's points hit

    def distance(self, xyz: np.ndarray) -> float:
        return float(np.abs(self.poses[:, :2] - xyz[:2]).max(axis=1).min())

    def look(self, name: str, mapper, scan_index: int) -> dict:
        labels, _ = mapper.query(self.points, with_probs=False)
        vox, _ = mapper.query(self.centres, with_probs=False)
        scored = self.gt > 0
        look = {
            "after_scan": scan_index,
            "accuracy": float(np.mean(labels[scored] == self.gt[scored])),
            "unknown_fraction": float(np.mean(labels[scored] == 0)),
            "voxel_labels": vox,
        }
        self.looks[name] = look
        return look

    def changed(self, a: str, b: str) -> float:
        """Fraction of the area's voxels labelled in `a` whose label differs in `b`."""
        la, lb = self.looks[a]["voxel_labels"], self.looks[b]["voxel_labels"]
        has = la > 0
        return float(np.mean(la[has] != lb[has])) if has.any() else float("nan")


def run(args) -> dict:
    import taichi as ti

    from benchmarks.common import device_line, median
    from tisem.backend import init_taichi
    from tisem.config import load_config
    from tisem.mapper import STAGES, Mapper
    from tisem.synth.sequence import SyntheticSequence, to_scan

    overrides = [f"mode={args.mode}", *args.overrides]
    if args.probe_chunk:
        overrides += [f"window_xy_m={args.probe_window}", "max_live_blocks=1000000000"]
    cfg = load_config(None, overrides).mapper
    init_taichi(args.arch, threads=args.threads)
    mapper = Mapper(cfg, profile=True)  # per-stage clocks (a ti.sync() between stages)
    seq = SyntheticSequence(args.scans, args.seed, "loop", points_per_ring=args.points_per_ring)
    area = StartArea(cfg.resolution_m)
    leave_m = cfg.window_xy_m + cfg.max_range_m  # farther than this: the area is all stored
    rows, times, points = [], [], []
    probe = None
    returned = None  # first scan back within range of the start area, after it was stored
    last_window_s, last_scan = 0.0, 0
    gib0 = gib_mappings()
    t_start = time.perf_counter()
    for i, frame in enumerate(seq):
        scan = to_scan(frame)
        ti.sync()
        t0 = time.perf_counter()
        mapper.integrate(scan)
        ti.sync()
        times.append(time.perf_counter() - t0)
        points.append(scan.num_points)
        if args.probe_chunk:
            gib = gib_mappings()
            if gib > gib0:
                probe = {
                    "scan": i,
                    "live_blocks": mapper.live_blocks,
                    "live_voxels": mapper.live_voxels,
                    "rss_mb": rss_mb(),
                    "vms_mb": vms_mb(),
                    "gib_mappings": [gib0, gib],
                    "blocks_before": rows[-1]["live_blocks"] if rows else None,
                }
                break
        if i < args.start_scans:
            area.add(scan)
            if i == args.start_scans - 1:
                area.finish()
                area.look("first", mapper, i)
        elif isinstance(area.poses, np.ndarray):
            if "stored" not in area.looks:
                if area.distance(scan.T_world_sensor[:3, 3]) > leave_m:
                    area.look("stored", mapper, i)
            elif returned is None and area.distance(scan.T_world_sensor[:3, 3]) < cfg.max_range_m:
                returned = i
        if (i + 1) % args.every == 0 or i + 1 == args.scans or args.probe_chunk:
            window_s = mapper.stage_seconds["window"]
            rows.append(
                {
                    "scan": i + 1,
                    "rss_mb": rss_mb(),
                    "vms_mb": vms_mb(),
                    "ms_per_scan": 1000 * median(times[-args.every :]),
                    "window_ms": 1000 * (window_s - last_window_s) / (i + 1 - last_scan),
                    "live_voxels": mapper.live_voxels,
                    "stored_voxels": mapper.stored_voxels,
                    "live_blocks": mapper.live_blocks,
                    "store_mb": mapper.store.nbytes / 2**20,
                    "store_disk_mb": mapper.store.disk_bytes / 2**20,
                    "elapsed_s": time.perf_counter() - t_start,
                }
            )
            last_window_s, last_scan = window_s, i + 1
            if not args.probe_chunk:
                r = rows[-1]
                print(
                    f"scan {r['scan']:5d}  rss {r['rss_mb']:6.0f} MB  "
                    f"{r['ms_per_scan']:6.1f} ms  live {r['live_voxels']:>9,}  "
                    f"stored {r['stored_voxels']:>10,}  "
                    f"blocks {r['live_blocks']:>7,}",
                    file=sys.stderr,
                    flush=True,
                )
    result = {
        "device": device_line(args.arch),
        "arch": args.arch,
        "threads": args.threads,
        "mode": cfg.mode,
        "config": vars(cfg),
        "scans": len(times),
        "points_per_ring": args.points_per_ring,
        "points_per_scan": median(points),
        "seed": args.seed,
        "every": args.every,
        "peak_rss_mb": peak_rss_mb(),
        "rows": rows,
        "ms_per_scan_median": 1000 * median(times[1:]),
        "ms_per_scan_p95": 1000 * float(np.percentile(times[1:], 95)) if len(times) > 1 else None,
        "wall_s": time.perf_counter() - t_start,
        "stage_ms_per_scan": {
            st: 1000 * mapper.stage_seconds[st] / max(len(times), 1) for st in STAGES
        },
    }
    if args.probe_chunk:
        result["probe"] = probe
        return result
    if isinstance(area.poses, np.ndarray):
        area.look("after", mapper, len(times) - 1)
        loop = {
            name: {k: v for k, v in look.items() if k != "voxel_labels"}
            for name, look in area.looks.items()
        }
        loop["voxels"] = int(len(area.centres))
        loop["points"] = int(len(area.points))
        ref = "stored" if "stored" in area.looks else "first"
        loop["changed_fraction"] = area.changed(ref, "after")
        loop["changed_vs"] = ref
        loop["returned_at_scan"] = returned
        result["loop_closure"] = loop
    if args.png:
        draw(result, args.png)
    return result


# --------------------------------------------------------------------------- output


def draw(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = r["rows"]
    scan = [x["scan"] for x in rows]
    fig, ax = plt.subplots(3, 1, figsize=(7, 6.5), sharex=True)
    ax[0].plot(scan, [x["rss_mb"] for x in rows], label="resident memory")
    ax[0].plot(scan, [x["store_mb"] for x in rows], label="of which host store in RAM")
    ax[0].plot(scan, [x["store_disk_mb"] for x in rows], label="host store on disk")
    ax[0].set_ylabel("MB")
    ax[0].legend(loc="upper left", fontsize=8)
    ax[1].plot(scan, [x["ms_per_scan"] for x in rows], color="C2")
    ax[1].set_ylabel(f"ms / scan\n(median of {r['every']})")
    ax[1].set_ylim(bottom=0)
    ax[2].plot(scan, [x["live_voxels"] / 1e6 for x in rows], label="live (Taichi field)")
    ax[2].plot(scan, [x["stored_voxels"] / 1e6 for x in rows], label="stored (host)")
    ax[2].set_ylabel("million voxels")
    ax[2].set_xlabel("scan")
    ax[2].legend(loc="upper left", fontsize=8)
    for a in ax:
        a.grid(alpha=0.3)
    lc = r.get("loop_closure", {})
    title = f"{r['scans']} scans, synthetic loop, mode {r['mode']}, {r['threads']} threads"
    if "after" in lc:
        title += (
            f"\nstart area accuracy {lc[lc['changed_vs']]['accuracy']:.3f} -> "
            f"{lc['after']['accuracy']:.3f}, {100 * lc['changed_fraction']:.1f}% of its "
            f"voxels relabelled"
        )
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=72)
    plt.close(fig)


def format_result(r: dict) -> str:
    lines = [
        f"device: {r['device']}",
        f"synthetic loop, {r['scans']} scans, {r['points_per_scan']:.0f} points per scan, "
        f"mode {r['mode']}, window +-{r['config']['window_xy_m']:.0f} m, "
        f"max_live_blocks {r['config']['max_live_blocks']:,}",
        "",
    ]
    if r.get("probe") is not None or "probe" in r:
        p = r.get("probe")
        if p is None:
            return "\n".join(lines + ["no second 1 GiB chunk was mapped in this drive"])
        return "\n".join(
            lines
            + [
                f"second 1 GiB host chunk mapped at scan {p['scan']}: "
                f"{p['live_blocks']:,} live leaf blocks ({p['blocks_before']:,} just before), "
                f"{p['live_voxels']:,} voxels, "
                f"VMS {p['vms_mb']:.0f} MB, RSS {p['rss_mb']:.0f} MB"
            ]
        )
    lines += [
        "| scan | RSS MB | ms / scan | live voxels | stored voxels | live blocks |",
        "| ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += [
        f"| {x['scan']} | {x['rss_mb']:.0f} | {x['ms_per_scan']:.1f} | {x['live_voxels']:,} "
        f"| {x['stored_voxels']:,} | {x['live_blocks']:,} |"
        for x in r["rows"]
    ]
    lines += [
        "",
        f"peak RSS {r['peak_rss_mb']:.0f} MB; {r['ms_per_scan_median']:.1f} ms per scan "
        f"(median), {r['ms_per_scan_p95']:.1f} ms (95th percentile); "
        f"wall {r['wall_s'] / 60:.1f} min",
        "mean ms per scan by stage: "
        + ", ".join(f"{k} {v:.1f}" for k, v in r["stage_ms_per_scan"].items()),
    ]
    lc = r.get("loop_closure")
    if lc:
        lines += [
            "",
            "| start area (GT of the first scans) | after scan | accuracy | unknown |",
            "| --- | ---: | ---: | ---: |",
        ]
        for name in ("first", "stored", "after"):
            if name in lc:
                x = lc[name]
                lines.append(
                    f"| {name} | {x['after_scan']} | {x['accuracy']:.4f} | "
                    f"{x['unknown_fraction']:.4f} |"
                )
        lines.append(
            f"\n{100 * lc['changed_fraction']:.2f}% of the area's {lc['voxels']:,} voxels "
            f"changed label between '{lc['changed_vs']}' and 'after'"
            + (
                f"; the sensor was back in range of the area from scan {lc['returned_at_scan']}"
                if lc["returned_at_scan"] is not None
                else " (the drive did not come back to the start)"
            )
        )

    return "\n".join(lines)


def main(argv=None) -> int:
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
