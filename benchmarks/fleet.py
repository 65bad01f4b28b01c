"""Fleet mapping against one serial run: wall time, the merged map's accuracy, memory.

    python benchmarks/fleet.py                                   # two robots, every mode
    python benchmarks/fleet.py --layout chunks --scans 120       # one long drive in 2 chunks
    python benchmarks/fleet.py --modes bki st --refine both --json fleet.json

Two synthetic robots of one world (tisem/synth/fleet_world.py), or one long drive cut into
`--chunks` time chunks, mapped (a) by one Mapper over every scan in time order, with
`--serial-threads` threads (a Ray task too, so that its memory is its own), and (b) by
`tisem.fleet` on a local Ray cluster of `--num-cpus` CPUs, one task per robot or chunk with
`--threads` threads each. Both maps are scored the
same way (the final-map protocol, by `tisem.reduce.score_log` on their tiled maps) and the
merged map is compared voxel by voxel with the serial one. The cluster's start-up is timed
apart: it is paid once per session, not per fleet.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import benchmark_main, device_line, peak_rss_mb, write_json

MODES = ("csm", "bki", "spatial", "adaptive", "st")


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--layout", choices=("robots", "chunks"), default="robots")
    p.add_argument("--robots", type=int, default=2)
    p.add_argument("--chunks", type=int, default=2)
    p.add_argument("--overlap-scans", type=int, default=20)
    p.add_argument("--scans", type=int, default=60, help="scans per robot (or of the drive)")
    p.add_argument("--points-per-ring", type=int, default=512)
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    p.add_argument(
        "--refine",
        choices=("auto", "off", "both"),
        default="auto",
        help="both: also a fleet without the seeded pass, for the kernel modes",
    )
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--threads", type=int, default=1, help="kernel threads per fleet task")
    p.add_argument("--serial-threads", type=int, default=2)
    p.add_argument("--num-cpus", type=int, default=2, help="CPUs of the local Ray cluster")
    p.add_argument("--out", type=Path, default=Path("results/bench_fleet"))
    p.add_argument("--json", type=Path)
    return p.parse_args(argv)


def make_data(args) -> Path:
    root = args.out / f"data_{args.layout}_{args.robots}x{args.scans}_{args.points_per_ring}"
    if (root / "sequences").is_dir():
        return root
    if args.layout == "robots":
        from tisem.synth.fleet_world import write_fleet

        write_fleet(
            root, args.robots, args.scans, points_per_ring=args.points_per_ring, progress=False
        )
    else:
        from tisem.synth.sequence import write_semantickitti

        write_semantickitti(
            root / "sequences" / "00",
            args.scans,
            points_per_ring=args.points_per_ring,
            progress=False,
        )
    return root


def score(map_dir: Path, logs, cfg) -> dict:
    from tisem.evaluate import Confusion
    from tisem.reduce import score_log

    conf = Confusion(cfg.mapper.num_classes)
    for spec in logs:
        conf.merge(
            Confusion.from_matrix(score_log(str(map_dir), spec, [(0, 1 << 62)], cfg.input)["final"])
        )
    m = conf.metrics()
    return {"miou": m["miou"], "accuracy": m["accuracy"]}


def write_serial(folder: Path, snap, cfg) -> Path:
    from tisem.config import to_dict
    from tisem.tiles import TILE_VOX, TileIndex, split_by_tile, write_index, write_tile

    config = to_dict(cfg)["mapper"]
    entries = [write_tile(folder, t, part, config) for t, part in split_by_tile(snap)]
    write_index(
        folder,
        TileIndex(
            cfg.mapper.resolution_m, cfg.mapper.num_classes, TILE_VOX, "serial", config, entries, {}
        ),
    )
    return folder


def serial_job(logs, run_config: dict, threads: int) -> dict:
    """The serial map in a process of its own (a Ray task): its map, time and memory."""
    from tisem.config import run_config_from_dict
    from tisem.map_compare import serial_snapshot

    snap, mapping, scans = serial_snapshot(logs, run_config_from_dict(run_config), threads)
    return {
        "snapshot": snap,
        "mapping_seconds": mapping,
        "scans": scans,
        "peak_mb": peak_rss_mb(),
        "device": device_line("cpu"),
    }


def fleet_row(mode, refine, data, logs, cfg, serial, args) -> dict:
    from tisem.fleet import FleetOptions, run_fleet
    from tisem.map_compare import compare_snapshots
    from tisem.tiles import TiledMap

    out = args.out / f"fleet_{args.layout}_{mode}_{refine}"
    options = FleetOptions(
        chunks=args.chunks if args.layout == "chunks" else 1,
        overlap_scans=args.overlap_scans,
        threads=args.threads,
        refine={"auto": None, "off": False}[refine],
        evaluate=False,
        reuse=False,
    )
    start = time.perf_counter()
    result = run_fleet(logs, cfg, out, options)
    wall = time.perf_counter() - start
    ((group, folder),) = result.maps.items()
    merged = TiledMap.open(folder)
    diff = compare_snapshots(merged.snapshot(), serial)
    tasks = result.report["tasks"].values()
    reducers = result.report["reduction"][group].values()
    merged_voxels = merged.voxels
    reduce_seconds = sum(r["seconds"] for r in reducers)
    return {
        "row": f"fleet ({'refined' if result.report['seconds'].get('refine') else 'apart'})",
        "mode": mode,
        "wall_seconds": wall,
        **score(folder, logs, cfg),
        "label_agreement": diff.label_agreement,
        "voxels": merged_voxels,
        "phase_seconds": result.report["seconds"],
        "task_seconds_per_scan": max(t["seconds_per_scan"] or 0 for t in tasks),
        "peak_worker_mb": max(t["peak_rss_mb"] for t in tasks),
        "peak_reducer_mb": max(r["peak_rss_mb"] for r in reducers),
        "reduce_seconds": reduce_seconds,
        "merge_us_per_voxel": 1e6 * reduce_seconds / max(merged_voxels, 1),
        "bytes_per_voxel": sum(r["bytes_read"] for r in reducers) / max(merged_voxels, 1),
        "tiles": len(merged.tile_keys),
        "failed": result.failed,
    }


def run(args) -> dict:
    from tisem.cluster import ray_cluster, submit
    from tisem.config import load_config, to_dict
    from tisem.logs import discover_logs

    args.out = args.out.resolve()
    data = make_data(args)
    logs = discover_logs([data])
    rows = []
    start = time.perf_counter()
    with ray_cluster(None, args.num_cpus):
        import ray

        ray.get(ray.remote(lambda: 0).remote())  # the cluster is up and has a worker
        cluster_seconds = time.perf_counter() - start
        for mode in args.modes:
            cfg = load_config(None, [*args.overrides, f"mode={mode}"])
            t0 = time.perf_counter()
            job = ray.get(
                submit(
                    serial_job,
                    cpus=args.serial_threads,
                    args=(logs, to_dict(cfg), args.serial_threads),
                )
            )
            wall = time.perf_counter() - t0
            serial, scans, device = job["snapshot"], job["scans"], job["device"]
            folder = write_serial(args.out / f"serial_{args.layout}_{mode}", serial, cfg)
            rows.append(
                {
                    "row": "serial",
                    "mode": mode,
                    "wall_seconds": wall,
                    "mapping_seconds": job["mapping_seconds"],
                    "seconds_per_scan": job["mapping_seconds"] / scans,
                    **score(folder, logs, cfg),
                    "label_agreement": 1.0,
                    "voxels": len(serial),
                    "peak_worker_mb": job["peak_mb"],
                }
            )
            refines = ["auto"] if args.refine == "auto" else ["off"]
            if args.refine == "both" and cfg.mapper.uses_kernel:
                refines = ["off", "auto"]
            for refine in refines:
                rows.append(fleet_row(mode, refine, data, logs, cfg, serial, args))
            logging.info("%s: %s", mode, rows[-1])
            if args.json:  # what is measured so far survives a later mode's failure
                write_json(args.json, {"partial": True, "rows": rows})
    # (the device as the serial task's Taichi runtime saw it: this process starts none)
    return {
        "device": device,
        "layout": args.layout,
        "data": str(data),
        "logs": len(logs),
        "scans": scans,
        "cluster_start_seconds": cluster_seconds,
        "num_cpus": args.num_cpus,
        "threads_per_task": args.threads,
        "serial_threads": args.serial_threads,
        "rows": rows,
    }


def format_result(result: dict) -> str:
    lines = [
        f"\ndevice: {result['device']}",
        f"{result['layout']}: {result['logs']} logs, {result['scans']} scans; Ray cluster "
        f"of {result['num_cpus']} CPUs (start {result['cluster_start_seconds']:.1f} s), "
        f"{result['threads_per_task']} thread(s) per task, serial "
        f"{result['serial_threads']} threads\n",
        "| mode | run | wall s | mIoU | accuracy | labels = serial | voxels | "
        "peak MB worker / reducer |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in result["rows"]:
        reducer = f" / {r['peak_reducer_mb']:.0f}" if "peak_reducer_mb" in r else ""
        lines.append(
            f"| {r['mode']} | {r['row']} | {r['wall_seconds']:.1f} | {r['miou']:.4f} | "
            f"{r['accuracy']:.4f} | {100 * r['label_agreement']:.3f} % | "
            f"{r['voxels']:,} | {r['peak_worker_mb']:.0f}{reducer} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
