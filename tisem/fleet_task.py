"""One fleet task in its own process: map a log (or a chunk of one) and write what it added.

    summary = map_task(task, run_config_dict, "out/tasks/robot1", threads=1)

The task maps its scans in a fresh Taichi runtime (one map per runtime, one runtime per
process). Before its own scans it may be given what the maps of other tasks already hold near
it, so that the voxels at its seams see the same history as in one serial run:
- warm-up scans (a chunk of a long log: the scans just before its first one), mapped but not
  counted;
- a seed map (`seed_dirs`: tiled maps of earlier tasks), restored into the mapper first.
What it writes is its contribution (`tisem.merge.contribution`: the map less the decayed seed
and warm-up state), as a tiled map under its folder, so that the reducers can read it tile by
tile. Nothing here knows about Ray.
"""

from __future__ import annotations

import logging
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tisem.config import run_config_from_dict
from tisem.errors import NothingMapped, SkippedScan
from tisem.logs import LogSpec, open_log, read_losses
from tisem.merge import contribution, merge_snapshots
from tisem.progress import seconds_per_scan
from tisem.snapshot import MapSnapshot
from tisem.tiles import (
    TILE_VOX,
    TiledMap,
    TileIndex,
    concat_snapshots,
    empty_snapshot,
    split_by_tile,
    write_index,
    write_tile,
)

log = logging.getLogger(__name__)

__all__ = ["MapTask", "map_task", "seed_snapshot"]


@dataclass(frozen=True)
class MapTask:
    """A log's scan positions first..last (inclusive), with `warmup` scans before `first`
    mapped first and not counted; `seed_from`: ids of the tasks whose maps seed this one;
    `anchor`: the map origin and time zero to use (`anchor_of`), None: the first scan's."""

    task_id: str
    log: LogSpec
    first: int
    last: int
    warmup: int = 0
    group: str = ""
    seed_from: tuple[str, ...] = field(default_factory=tuple)
    anchor: dict | None = None

    def to_dict(self) -> dict:
        return {
            "task_id": self.task_id,
            "log": self.log.to_dict(),
            "first": self.first,
            "last": self.last,
            "warmup": self.warmup,
            "group": self.group,
            "seed_from": list(self.seed_from),
            "anchor": self.anchor,
        }


def seed_snapshot(
    seed_dirs: list[str],
    footprint: set[tuple[int, int]],
    tau_s: float,
    num_classes: int,
    resolution_m: float,
) -> MapSnapshot:
    """The merged voxels of the seed maps in the tiles of `footprint`."""
    maps = [TiledMap.open(d, cache_tiles=1) for d in seed_dirs]
    parts = []
    for tile in sorted(footprint):
        held = [m.tile(tile) for m in maps if m.entry(tile) is not None]
        if held:
            parts.append(merge_snapshots(held, tau_s))
    return concat_snapshots(parts, num_classes, resolution_m)


def dilate(tiles: set[tuple[int, int]]) -> set[tuple[int, int]]:
    """The tiles and their 8 neighbours: a kernel (<= a few metres) never reaches further."""
    return {(x + dx, y + dy) for x, y in tiles for dx in (-1, 0, 1) for dy in (-1, 0, 1)}


def _start_map(
    mapper, seed: MapSnapshot | None, anchor: dict | None, first_pose: np.ndarray, stamp_s: float
) -> None:
    """Give the fresh `mapper` its origin and time zero before the first scan: the group's
    `anchor` (the serial run's: the same float rounding in every task) or what the first scan
    would have given it, and the `seed` voxels."""
    from tisem.geometry import block_aligned_origin

    res = mapper.geometry.resolution_m
    if anchor is not None:
        origin, t0 = np.asarray(anchor["origin_vox"], np.int64), float(anchor["t0"])
    else:
        origin, t0 = block_aligned_origin(np.floor(first_pose[:3, 3] / res)), float(stamp_s)
    center = np.floor((first_pose[:3, 3] - origin * res) / res).astype(np.int64)
    if seed is None:
        seed = empty_snapshot(mapper.C, res)
    mapper.restore(
        seed,
        {
            "origin_vox": origin.tolist(),
            "t0": t0,
            "center_vox": center.tolist(),
            "scans": 0,
            "last_stamp_s": None,
        },
    )


def anchor_of(first_pose: np.ndarray, stamp_s: float, resolution_m: float) -> dict:
    """The origin and time zero a map whose first scan is this one gets (`_start_map`)."""
    from tisem.geometry import block_aligned_origin

    origin = block_aligned_origin(np.floor(first_pose[:3, 3] / resolution_m))
    return {"origin_vox": origin.tolist(), "t0": float(stamp_s)}


def map_task(
    task: MapTask,
    run_config: dict,
    out_dir: str | Path,
    *,
    threads: int = 1,
    arch: str = "cpu",
    seed_dirs: list[str] | None = None,
    footprint: list[list[int]] | None = None,
    tile_vox: int = TILE_VOX,
) -> dict:
    """Map the task (module docstring) into `out_dir`; returns its summary (plain JSON)."""
    from tisem.backend import describe, init_taichi
    from tisem.mapper import Mapper

    started = time.perf_counter()
    cfg = run_config_from_dict(run_config)
    init_taichi(arch, threads=threads)
    mapper = Mapper(cfg.mapper)
    tau = cfg.mapper.decay_tau_s
    res, num_classes = cfg.mapper.resolution_m, cfg.mapper.num_classes
    start = max(task.first - task.warmup, 0)
    scans = open_log(task.log, start, task.last, input=cfg.input, num_classes=num_classes)
    seed = None
    if seed_dirs:
        seed = seed_snapshot(
            seed_dirs, dilate({tuple(t) for t in footprint or []}), tau, num_classes, res
        )
    own_from = task.first - start
    state_before = None
    seconds, skipped, mapped, first_stamp, last_stamp = [], [], 0, None, None
    trajectory = []
    for position, item in enumerate(scans):
        own = position >= own_from
        if isinstance(item, SkippedScan):
            if own:
                skipped.append({"index": item.index, "reason": item.reason})
            continue
        if mapper.origin_vox is None and (seed is not None or task.anchor is not None):
            _start_map(mapper, seed, task.anchor, item.T_world_sensor, item.stamp_s)
        if own and state_before is None:
            state_before = mapper.snapshot()  # the seed and the warm-up, taken out at the end
        t0 = time.perf_counter()
        try:
            mapper.integrate(item)
        except ValueError as exc:  # a scan the mapper refuses: skipped, as in a run
            if own:
                skipped.append({"index": item.index, "reason": str(exc)})
            continue
        if own:
            seconds.append(time.perf_counter() - t0)
            mapped += 1
            first_stamp = item.stamp_s if first_stamp is None else first_stamp
            last_stamp = item.stamp_s
            trajectory.append(item.T_world_sensor[:3, 3].tolist())
    if not mapped and skipped:
        # a log that cannot be read at all (every scan refused) is a failed task, reported
        # with the first reason, not an empty map that looks like a success
        raise NothingMapped(
            f"{task.task_id}: none of its {len(skipped)} scans could be "
            f"mapped; first: {skipped[0]['reason']}"
        )
    final = mapper.snapshot()
    if state_before is None:  # no scan of the task's own was mapped
        state_before = final
    own = contribution(final, state_before, tau)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)  # the index is written even with no tile
    entries = [
        write_tile(out_dir, tile, part, run_config["mapper"])
        for tile, part in split_by_tile(own, tile_vox)
    ]
    summary = {
        "task": task.to_dict(),
        "scans": mapped,
        "skipped": skipped,
        "read_losses": read_losses(scans),
        "seconds_per_scan": seconds_per_scan(seconds),
        "mapping_seconds": float(np.sum(seconds)),
        "wall_seconds": time.perf_counter() - started,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "voxels": len(own),
        "seed_voxels": 0 if seed is None else len(seed),
        "first_stamp_s": first_stamp,
        "last_stamp_s": last_stamp,
        # every 10th position is plenty for a picture
        "trajectory_xy": np.asarray(trajectory)[::10, :2].round(2).tolist() if trajectory else [],
        "device": describe(),
        "tiles": [e["tile"] for e in entries],
        "bytes": int(sum(e["bytes"] for e in entries)),
    }
    write_index(
        out_dir,
        TileIndex(
            res,
            num_classes,
            tile_vox,
            task.log.world_frame,
            run_config["mapper"],
            entries,
            {"summary": summary},
        ),
    )
    return summary
