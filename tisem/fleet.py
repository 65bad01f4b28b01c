"""Distributed mapping on Ray: many logs (or one long log in chunks) into merged tiled maps.

    result = run_fleet(["data/robots"], load_config(None, ["mode=bki"]), "results/fleet",
                       FleetOptions(chunks=1, threads=1))
    tisem.tiles.TiledMap.open(result.maps["robots"]).query(points)

The steps (fleet.json records each one's seconds and what it did):
1. plan: every log (`tisem.logs`), cut into `chunks` time chunks, is one task; a chunk maps
   `overlap_scans` scans before its first one as a warm-up, so that the voxels at its seam see
   the scans they would in one run. Logs are grouped by world frame: a group is one merged map.
2. map: one Ray task per log or chunk (`tisem.fleet_task.map_task`), each in its own worker
   process with its kernel threads as its CPUs; it writes its contribution as a tiled map.
3. refine (kernel modes): a task whose area overlaps tasks that started before it maps its
   scans again seeded with their maps, so that it updates the voxels they created as a serial
   run would (exact for bki, docs/scale.md measures adaptive and st).
4. reduce: reducers (Ray tasks) each own a set of tiles and merge them from the task maps
   (`tisem.reduce`); the index is written last. The map of a group that fits
   `max_merged_voxels` is also written as map.npz, map.ply and map_bev.png.
5. score (`tisem.fleet_report`, with the per-group files and fleet.json): each log's scans
   are looked up in its group's merged map (final-map protocol), one Ray task per log, into
   the group's metrics.json.
A task that fails is retried as Ray allows, then reported (fleet.json "failed" and "missing");
the others are merged. Task maps of an earlier run of the same plan are kept (`reuse`).
"""

from __future__ import annotations

import dataclasses
import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

from tisem import cluster
from tisem.config import RunConfig, to_dict
from tisem.errors import DatasetError
from tisem.fleet_report import fleet_report, report_json, score_groups, write_group_files
from tisem.fleet_task import MapTask, anchor_of, dilate, map_task
from tisem.logs import LogSpec, discover_logs, first_pose, log_length
from tisem.reduce import assign_tiles, reduce_tiles
from tisem.tiles import TILE_VOX, TileIndex, is_tiled_map, write_index

log = logging.getLogger(__name__)

__all__ = ["FleetOptions", "FleetResult", "plan_tasks", "run_fleet", "group_logs"]


@dataclass
class FleetOptions:
    """How a fleet runs (module docstring). `refine` None: on in the kernel modes."""

    chunks: int = 1
    overlap_scans: int = 20
    refine: bool | None = None
    reducers: int = 2
    threads: int = 1
    retries: int = 1
    address: str | None = None
    num_cpus: int | None = None
    max_merged_voxels: int = 20_000_000
    evaluate: bool = True
    world_frame: str | None = None  # declare that every log's poses are in this frame
    tile_vox: int = TILE_VOX
    arch: str = "cpu"
    reuse: bool = True
    progress: bool = True  # bars counting each step's tasks as they end

    def validate(self) -> None:
        if self.chunks < 1 or self.overlap_scans < 0 or self.reducers < 1 or self.threads < 1:
            raise ValueError("need chunks >= 1, overlap_scans >= 0, reducers >= 1, threads >= 1")
        if self.tile_vox % 32:
            raise ValueError(
                f"tile_vox must be a multiple of 32 (the top cell), got {self.tile_vox}"
            )


@dataclass
class FleetResult:
    """A finished fleet: its folder, each group's merged tiled map, fleet.json's content."""

    out_dir: Path
    maps: dict[str, Path]
    report: dict
    failed: dict[str, str] = field(default_factory=dict)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "map"


def group_logs(logs: list[LogSpec]) -> dict[str, list[LogSpec]]:
    """Logs by world frame, named by the frame (a sequence in its own frame: by the log)."""
    frames: dict[str, list[LogSpec]] = {}
    for spec in logs:
        frames.setdefault(spec.world_frame, []).append(spec)
    groups: dict[str, list[LogSpec]] = {}
    for frame, members in frames.items():
        own = frame.startswith(("kitti:", "mcap:")) and len(members) == 1
        name = _slug(members[0].name if own else frame)
        while name in groups:
            name += "_"
        groups[name] = members
    return groups


def plan_tasks(
    groups: dict[str, list[LogSpec]], options: FleetOptions, input: str = "predictions"
) -> list[MapTask]:
    """One task per log, or per chunk of a log (module docstring, step 1)."""
    tasks = []
    for group, members in groups.items():
        for spec in members:
            whole = MapTask(spec.name, spec, 0, 1 << 62, 0, group)
            if options.chunks == 1:
                tasks.append(whole)
                continue
            try:
                n = log_length(spec, input)
            except (DatasetError, OSError, ValueError) as exc:
                # a log that cannot be read is not cut: its one task fails with this reason,
                # reported like any failed task, and the other logs are mapped
                log.warning("%s: not cut into chunks, it cannot be read: %s", spec.name, exc)
                tasks.append(whole)
                continue
            bounds = [round(k * n / options.chunks) for k in range(options.chunks + 1)]
            for k in range(options.chunks):
                if bounds[k + 1] > bounds[k]:
                    tasks.append(
                        MapTask(
                            f"{spec.name}#chunk{k}",
                            spec,
                            bounds[k],
                            bounds[k + 1] - 1,
                            options.overlap_scans if k else 0,
                            group,
                        )
                    )
    return tasks


def group_anchors(groups: dict[str, list[LogSpec]], cfg: RunConfig) -> dict[str, dict]:
    """Per group, the origin and time zero of a serial run over its logs (that of its
    earliest first scan, among the logs that tell it cheaply: SemanticKITTI): every task of
    the group maps in those local coordinates, so they round floats alike (and as the serial
    run does)."""
    anchors = {}
    for group, members in groups.items():
        firsts = [f for f in (first_pose(spec, cfg.input) for spec in members) if f is not None]
        if firsts:
            pose, stamp = min(firsts, key=lambda f: f[1])
            anchors[group] = anchor_of(pose, stamp, cfg.mapper.resolution_m)
    return anchors


def _finished(folder: Path, task: MapTask, mapper_config: dict) -> dict | None:
    """The summary of a task map an earlier run left in `folder` for the same task and
    config, or None."""
    if not is_tiled_map(folder):
        return None
    try:
        index = TileIndex.read(folder)
    except (OSError, ValueError):
        return None
    summary = index.meta.get("summary") or {}
    if summary.get("task") != task.to_dict() or index.mapper_config != mapper_config:
        return None
    return summary


def _map_all(
    tasks: dict[str, MapTask],
    folders: dict[str, Path],
    cfg: RunConfig,
    options: FleetOptions,
    seeds: dict[str, list[str]] | None = None,
    footprints: dict[str, list] | None = None,
    what: str = "mapping",
) -> tuple[dict, dict]:
    """Run (or reuse) every task; ({id: summary}, {id: reason}); `what`: the progress bar's
    name."""
    config = to_dict(cfg)
    done, refs = {}, {}
    for task_id, task in tasks.items():
        kept = _finished(folders[task_id], task, config["mapper"]) if options.reuse else None
        if kept is not None:
            done[task_id] = kept
            continue
        refs[task_id] = cluster.submit(
            map_task,
            cpus=options.threads,
            retries=options.retries,
            args=(task, config, str(folders[task_id])),
            kwargs={
                "threads": options.threads,
                "arch": options.arch,
                "seed_dirs": (seeds or {}).get(task_id),
                "footprint": (footprints or {}).get(task_id),
                "tile_vox": options.tile_vox,
            },
        )
    ran, failed = cluster.gather(refs, what if options.progress else None)
    return {**done, **ran}, failed


def _refine_plan(tasks: dict[str, MapTask], summaries: dict[str, dict], folders: dict[str, Path]):
    """The tasks to map again seeded (step 3): {id: (seeded task, seed folders)}."""
    plan = {}
    for task_id, task in tasks.items():
        mine = summaries.get(task_id)
        if mine is None or mine["first_stamp_s"] is None:
            continue
        reach = dilate({tuple(t) for t in mine["tiles"]})
        earlier = [
            other
            for other, s in summaries.items()
            if other != task_id
            and tasks[other].group == task.group
            and s["first_stamp_s"] is not None
            and (s["first_stamp_s"], other) < (mine["first_stamp_s"], task_id)
            and reach & {tuple(t) for t in s["tiles"]}
        ]
        if earlier:
            seeded = dataclasses.replace(task, warmup=0, seed_from=tuple(sorted(earlier)))
            plan[task_id] = (seeded, [str(folders[e]) for e in sorted(earlier)])
    return plan


def run_fleet(
    logs: list[LogSpec] | list[str],
    cfg: RunConfig,
    out_dir: str | Path,
    options: FleetOptions | None = None,
) -> FleetResult:
    """Map, refine, reduce and score (module docstring); returns the result."""
    options = options or FleetOptions()
    options.validate()
    out_dir = Path(out_dir).resolve()
    clock, seconds = time.perf_counter(), {}
    specs = [s if isinstance(s, LogSpec) else None for s in logs]
    if any(s is None for s in specs):
        specs = discover_logs([str(Path(p).resolve()) for p in logs])
    if options.world_frame:
        specs = [dataclasses.replace(s, world_frame=options.world_frame) for s in specs]
    groups = group_logs(specs)
    anchors = group_anchors(groups, cfg)
    tasks = {
        t.task_id: dataclasses.replace(t, anchor=anchors.get(t.group))
        for t in plan_tasks(groups, options, cfg.input)
    }
    folders = {tid: out_dir / "tasks" / _slug(tid) for tid in tasks}
    seconds["plan"] = time.perf_counter() - clock
    refine = options.refine if options.refine is not None else cfg.mapper.uses_kernel
    with cluster.ray_cluster(options.address, options.num_cpus):
        clock = time.perf_counter()
        summaries, failed = _map_all(tasks, folders, cfg, options)
        seconds["map"] = time.perf_counter() - clock
        final_dirs = {tid: folders[tid] for tid in summaries}
        refined = {}
        if refine:
            clock = time.perf_counter()
            plan = _refine_plan(tasks, summaries, folders)
            again = {tid: seeded for tid, (seeded, _) in plan.items()}
            refolders = {
                tid: folders[tid].with_name(folders[tid].name + ".refined") for tid in plan
            }
            refined, refine_failed = _map_all(
                again,
                refolders,
                cfg,
                options,
                {tid: s for tid, (_, s) in plan.items()},
                {tid: summaries[tid]["tiles"] for tid in plan},
                what="refining",
            )
            for tid in refined:
                final_dirs[tid] = refolders[tid]
            for tid, reason in refine_failed.items():
                log.warning("refining %s failed (%s): its unrefined map is merged", tid, reason)
            failed.update({f"{tid} (refine)": r for tid, r in refine_failed.items()})
            seconds["refine"] = time.perf_counter() - clock
        finals = {tid: refined.get(tid, s) for tid, s in summaries.items()}
        clock = time.perf_counter()
        maps, reduction = _reduce(groups, tasks, finals, final_dirs, cfg, options, out_dir)
        seconds["reduce"] = time.perf_counter() - clock
        clock = time.perf_counter()
        metrics = (
            score_groups(groups, tasks, finals, maps, cfg, options.progress)
            if options.evaluate
            else {}
        )
        seconds["score"] = time.perf_counter() - clock
    clock = time.perf_counter()
    for name, folder in maps.items():
        write_group_files(
            folder, groups[name], tasks, finals, failed, metrics.get(name), cfg, options
        )
    seconds["files"] = time.perf_counter() - clock
    report = fleet_report(options, cfg, tasks, finals, failed, maps, reduction, metrics, seconds)
    (out_dir / "fleet.json").write_text(report_json(report))
    return FleetResult(out_dir, maps, report, dict(failed))


def _reduce(groups, tasks, finals, final_dirs, cfg, options, out_dir):
    """Step 4: {group: merged map folder}, {group: reducer reports}."""
    config = to_dict(cfg)["mapper"]
    refs, maps, layout = {}, {}, {}
    for group, members in groups.items():
        held: dict[tuple[int, int], list[str]] = {}
        for tid in sorted(finals):
            if tasks[tid].group == group:
                for tile in finals[tid]["tiles"]:
                    held.setdefault(tuple(tile), []).append(str(final_dirs[tid]))
        folder = out_dir / "maps" / group
        folder.mkdir(parents=True, exist_ok=True)
        maps[group] = folder
        layout[group] = members[0].world_frame
        for r, owned in enumerate(assign_tiles(list(held), options.reducers)):
            if owned:
                work = [(list(t), held[t]) for t in owned]
                refs[f"{group}/reducer{r}"] = cluster.submit(
                    reduce_tiles,
                    cpus=1,
                    retries=options.retries,
                    args=(str(folder), work, cfg.mapper.decay_tau_s, config),
                )
    done, failed = cluster.gather(refs, "merging tiles" if options.progress else None)
    if failed:
        raise RuntimeError(f"reducers failed: {failed}")
    reduction = {}
    for group, folder in maps.items():
        mine = {k: v for k, v in done.items() if k.startswith(group + "/")}
        entries = [e for v in mine.values() for e in v["entries"]]
        write_index(
            folder,
            TileIndex(
                cfg.mapper.resolution_m,
                cfg.mapper.num_classes,
                options.tile_vox,
                layout[group],
                config,
                entries,
                {"tasks": sorted(t for t in finals if tasks[t].group == group)},
            ),
        )
        reduction[group] = {
            k: {x: v for x, v in r.items() if x != "entries"} for k, r in mine.items()
        }
    return maps, reduction
