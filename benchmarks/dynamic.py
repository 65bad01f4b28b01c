"""Moving objects: DynamicMap's SA / DA / AA, ghost trails and semantic metrics, with and
without free space and per-class decay, and csm as the floor.

    python benchmarks/dynamic.py --synthetic --scans 150 --json out/dynamic.json
    python benchmarks/dynamic.py --data ../shared/data/semantickitti_08_mini

Ground truth: which points are dynamic (SemanticKITTI's moving ids 252-259; on the synthetic
street with its extra movers, points on a mover that is under way or elsewhere at the end). The
maps are fed the labels alone (the input's motion labels are withheld, so that motion is found,
not read).

* sa / da / aa: every ground-truth point of every scan is kept when its voxel is in the final
  static map (a voxel with evidence, not seen empty); SA = static points kept, DA = dynamic
  points not kept, AA = sqrt(SA * DA) (Zhang et al., ITSC 2023).
* trail_voxels: voxels of the static map labelled with a movable class where a dynamic point
  was once and no object of such a class is at the end (no static point of one in any scan,
  none in the last scan).
* miou_online / accuracy_online: every point scored right after its scan is fused (moving
  points when they were seen; a point the map flagged dynamic with the network's label, as a
  run scores it); iou_car_online / iou_person_online alone. miou_final_static /
  accuracy_final_static: the static points on the final map. The final-map protocol alone
  rewards keeping ghosts (a trail holds the class its points had), so both are reported.
* da_bound (once per data set): the highest DA any map of voxels at this resolution can reach
  while it keeps every static point, 1 - (dynamic points in a voxel that also holds a static
  point of some scan) / (dynamic points): wheels and feet share the ground's voxels.
  da_bound_sa99: the same for a map that keeps 99 % of the static points (the SA target),
  giving up the shared voxels with the most dynamic points per static point first.
* seconds_per_scan: mean `integrate` time after the first scans (compilation); stages_ms: the
  mapper's per-stage profile (free_space: flags, hits and rays).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import KITTI_MINI, benchmark_main, device_line  # noqa: E402
from tisem.backend import init_taichi  # noqa: E402
from tisem.config import MapperConfig, RunConfig, set_value  # noqa: E402
from tisem.evaluate import Confusion, online_labels  # noqa: E402
from tisem.labels import MOVABLE_CLASSES  # noqa: E402
from tisem.mapper import Mapper  # noqa: E402
from tisem.scan import Scan  # noqa: E402
from tisem.store_segments import pack  # noqa: E402

WARMUP_SCANS = 3
SA_TARGET = 0.99  # DynamicMap's static accuracy a map must keep (the DA bound at this SA)
TAU_MOVABLE_S = 1.0
# (method, config overrides)
METHODS = (
    ("tisem", {}),
    ("tisem+free_space", {"free_space": True}),
    ("tisem+class_decay", {"tau_movable_s": TAU_MOVABLE_S}),
    ("tisem+free_space+class_decay", {"free_space": True, "tau_movable_s": TAU_MOVABLE_S}),
    ("csm", {"mode": "csm"}),
)


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, default=None, help="SemanticKITTI sequence folder")
    p.add_argument(
        "--synthetic", action="store_true", help="the synthetic street with its extra movers"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scans", type=int, default=150)
    p.add_argument(
        "--methods",
        default=",".join(m for m, _ in METHODS),
        help="comma-separated subset of the rows",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a mapper setting for every row (e.g. free_margin_fraction=0.1)",
    )
    p.add_argument("--json", type=Path)
    return p.parse_args(argv)


def load(args) -> tuple[list[Scan], str]:
    """Scans with ground truth and its motion flags (gt_moving); input motion withheld."""
    data = args.data
    if data is None and not args.synthetic:
        data = KITTI_MINI
    if data is not None:
        from tisem.io.semantickitti import SemanticKittiSequence

        scans = [s for s in SemanticKittiSequence(data, last=None) if isinstance(s, Scan)]
        scans = scans[: args.scans]
        what = f"{data} ({len(scans)} scans)"
    else:
        from tisem.synth.sequence import SyntheticSequence, to_scan

        seq = SyntheticSequence(args.scans, seed=args.seed, movers=True)
        scans = [to_scan(f) for f in seq]
        what = f"synthetic street with movers, seed {args.seed} ({len(scans)} scans)"
    for s in scans:
        if s.gt_labels is None or s.gt_moving is None:
            raise SystemExit(f"{s.name}: no ground truth (labels and motion) to score")
    return [dataclasses.replace(s, moving=None) for s in scans], what


def da_bound(scans: list[Scan], resolution_m: float, min_sa: float = 1.0) -> float:
    """The highest DA a map of voxels at this resolution can reach while it keeps at least
    `min_sa` of the static points (every one at 1).

    The map without a voxel loses the voxel's points of every scan: the voxels of dynamic
    points alone go first, then those that also hold static points, the most dynamic points
    per static point first, while the static points lost stay within 1 - min_sa (greedy, so
    within one voxel of the best such map; exact at 1, where no shared voxel goes).
    """
    static = np.concatenate(
        [pack(np.floor(s.points_world()[~s.gt_moving] / resolution_m)) for s in scans]
    )
    dynamic = np.concatenate(
        [pack(np.floor(s.points_world()[s.gt_moving] / resolution_m)) for s in scans]
    )
    if len(dynamic) == 0:
        return 1.0
    keys, which = np.unique(np.concatenate([static, dynamic]), return_inverse=True)
    n_static = np.bincount(which[: len(static)], minlength=len(keys))
    n_dynamic = np.bincount(which[len(static) :], minlength=len(keys))
    shared = np.flatnonzero((n_static > 0) & (n_dynamic > 0))
    removed = n_dynamic[n_static == 0].sum()
    order = shared[np.argsort(-n_dynamic[shared] / n_static[shared], kind="stable")]
    allowed = (1.0 - min_sa) * len(static)
    take = np.searchsorted(np.cumsum(n_static[order]), allowed, side="right")
    removed += n_dynamic[order[:take]].sum()
    return float(removed) / len(dynamic)


def run_method(scans: list[Scan], cfg: MapperConfig) -> dict:
    mapper = Mapper(cfg, profile=True)
    online = Confusion()
    seconds = []
    for k, scan in enumerate(scans):
        if k == WARMUP_SCANS:
            mapper.stage_seconds = dict.fromkeys(mapper.stage_seconds, 0.0)
        t = time.perf_counter()
        report = mapper.integrate(scan)
        if k >= WARMUP_SCANS:
            seconds.append(time.perf_counter() - t)
        labels, _ = mapper.query(scan.points_world(), with_probs=False)
        online.add(scan.gt_labels, online_labels(labels, scan, report.dynamic))
    timed = max(len(seconds), 1)
    snap = mapper.snapshot()
    static = snap.static_map()
    in_map = pack(static.keys[static.counts.sum(axis=1) > 0])
    in_map.sort()
    res = cfg.resolution_m
    kept_static = kept_dynamic = n_static = n_dynamic = 0
    final = Confusion()
    occupied_by_movable, trail_region = [], []
    for k, scan in enumerate(scans):
        world = scan.points_world()
        keys = pack(np.floor(world / res))
        pos = np.clip(np.searchsorted(in_map, keys), 0, max(len(in_map) - 1, 0))
        kept = in_map[pos] == keys if len(in_map) else np.zeros(len(keys), bool)
        dyn = scan.gt_moving
        kept_static += int(kept[~dyn].sum())
        n_static += int((~dyn).sum())
        kept_dynamic += int(kept[dyn].sum())
        n_dynamic += int(dyn.sum())
        movable = np.isin(scan.gt_labels, MOVABLE_CLASSES)
        trail_region.append(keys[dyn])
        occupied_by_movable.append(keys[movable & (~dyn | (k == len(scans) - 1))])
    for scan in scans:
        static_pts = ~scan.gt_moving
        labels, _ = mapper.query(scan.points_world()[static_pts], with_probs=False)
        final.add(scan.gt_labels[static_pts], labels)
    movable_voxels = pack(static.keys[np.isin(static.labels(), MOVABLE_CLASSES)])
    trails = int(
        (
            np.isin(movable_voxels, np.concatenate(trail_region))
            & ~np.isin(movable_voxels, np.concatenate(occupied_by_movable))
        ).sum()
    )
    sa = kept_static / max(n_static, 1)
    da = 1.0 - kept_dynamic / max(n_dynamic, 1)
    on, fin = online.metrics(), final.metrics()
    iou = on["per_class_iou"]
    return {
        "sa": sa,
        "da": da,
        "aa": float(np.sqrt(sa * da)),
        "trail_voxels": trails,
        "miou_online": on["miou"],
        "accuracy_online": on["accuracy"],
        "iou_car_online": iou.get("car"),
        "iou_person_online": iou.get("person"),
        "miou_final_static": fin["miou"],
        "accuracy_final_static": fin["accuracy"],
        "per_class_iou_final_static": fin["per_class_iou"],
        "seconds_per_scan": float(np.mean(seconds)) if seconds else float("nan"),
        "stages_ms": {s: v / timed * 1000 for s, v in mapper.stage_seconds.items()},
        "static_points": n_static,
        "dynamic_points": n_dynamic,
        "voxels": len(snap),
        "empty_voxels": int(snap.empty().sum()),
    }


def run(args) -> dict:
    init_taichi("cpu", threads=2)
    scans, what = load(args)
    chosen = args.methods.split(",")
    common = RunConfig()  # the --set values hold for every row, the resolution among them
    for assignment in args.set:
        set_value(common, assignment)
    bound = da_bound(scans, common.mapper.resolution_m)
    bound_sa99 = da_bound(scans, common.mapper.resolution_m, min_sa=SA_TARGET)
    print(
        f"da_bound {bound:.4f} (dynamic points in no voxel of a static point), "
        f"{bound_sa99:.4f} with SA {SA_TARGET}",
        flush=True,
    )
    rows = []
    for name, overrides in METHODS:
        if name not in chosen:
            continue
        init_taichi("cpu", threads=2)  # one map per runtime
        cfg = RunConfig(mapper=MapperConfig(**overrides))
        for assignment in args.set:
            set_value(cfg, assignment)
        row = {"method": name, **run_method(scans, cfg.mapper)}
        rows.append(row)
        print(format_row(row), flush=True)
    return {
        "data": what,
        "device": device_line("cpu"),
        "settings": args.set,
        "da_bound": bound,
        "da_bound_sa99": bound_sa99,
        "rows": rows,
    }


COLUMNS = (
    "sa",
    "da",
    "aa",
    "trail_voxels",
    "miou_online",
    "accuracy_online",
    "iou_car_online",
    "iou_person_online",
    "miou_final_static",
    "accuracy_final_static",
    "seconds_per_scan",
)


def format_row(row: dict) -> str:
    cells = [row["method"]] + [
        f"{row[c]:.4f}" if isinstance(row[c], float) else str(row[c]) for c in COLUMNS
    ]  # (None: a class absent from the data)
    return "| " + " | ".join(cells) + " |"


def format_result(result: dict) -> str:
    lines = [
        f"{result['data']}; {result['device']}",
        f"da_bound {result['da_bound']:.4f}: the highest DA of a voxel map that keeps every "
        f"static point; {result['da_bound_sa99']:.4f} for one that keeps {SA_TARGET:.0%} of them",
        "",
        "| method | " + " | ".join(COLUMNS) + " |",
        "|---" * (len(COLUMNS) + 1) + "|",
    ]
    lines += [format_row(r) for r in result["rows"]]
    lines += ["", "stages, ms per scan:"]
    for r in result["rows"]:
        lines.append(
            f"  {r['method']}: " + ", ".join(f"{k} {v:.1f}" for k, v in r["stages_ms"].items())
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
