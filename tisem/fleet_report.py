"""What a fleet reports once its maps are merged: scores, per-group files and fleet.json.

Step 5 of `tisem.fleet` (each log scored in its group's merged map, one Ray task per log),
then each group's metrics.json and, when the merged map fits, its usual map files, and the
content of fleet.json: what ran, what failed and which scans are missing (and what a damaged
recording lost: `lost` lines). Apart from the planning and mapping in `tisem.fleet` because
this part only reads what those steps left.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

from tisem import cluster
from tisem.config import RunConfig, to_dict
from tisem.evaluate import Confusion
from tisem.logs import LogSpec
from tisem.reduce import score_log
from tisem.report import METRIC_KEYS
from tisem.tiles import TiledMap

if TYPE_CHECKING:
    from tisem.fleet import FleetOptions
    from tisem.fleet_task import MapTask

# one logger for every line of a fleet, as the fleet app's own (tisem.commands.fleet)
log = logging.getLogger("tisem.fleet")

__all__ = ["score_groups", "write_group_files", "fleet_report", "report_json"]


def score_groups(
    groups: dict[str, list[LogSpec]],
    tasks: dict[str, MapTask],
    finals: dict[str, dict],
    maps: dict[str, Path],
    cfg: RunConfig,
    progress: bool = False,
) -> dict:
    """Step 5: {group: {"final": metrics, "input": metrics, "scans": n}}; `progress`: a bar
    counting the logs scored."""
    refs, of_group = {}, {}
    for group in maps:
        for spec in groups[group]:
            ranges = [
                (tasks[t].first, tasks[t].last) for t in sorted(finals) if tasks[t].log == spec
            ]
            if ranges:
                key = f"{group}/{spec.name}"
                of_group[key] = group
                refs[key] = cluster.submit(
                    score_log, cpus=1, args=(str(maps[group]), spec, ranges, cfg.input)
                )
    done, failed = cluster.gather(refs, "scoring" if progress else None)
    metrics = {}
    for group in maps:
        final, network = Confusion(cfg.mapper.num_classes), Confusion(cfg.mapper.num_classes)
        scans = 0
        for key, r in done.items():
            if of_group[key] == group:
                final.merge(Confusion.from_matrix(r["final"]))
                network.merge(Confusion.from_matrix(r["input"]))
                scans += r["scans"]
        metrics[group] = {
            "scans": scans,
            "final": _summary(final),
            "input": _summary(network),
            "failed": {k: v for k, v in failed.items() if of_group[k] == group},
        }
    return metrics


def _summary(conf: Confusion) -> dict:
    m = conf.metrics()
    return {k: m[k] for k in METRIC_KEYS}


def write_group_files(
    folder: Path,
    members: list[LogSpec],
    tasks: dict[str, MapTask],
    finals: dict[str, dict],
    failed: dict[str, str],
    metrics: dict | None,
    cfg: RunConfig,
    options: FleetOptions,
) -> None:
    """metrics.json of a group, and the usual map files when the merged map fits."""
    tiled = TiledMap.open(folder)
    mine = [t for t in tasks if tasks[t].log in members]
    body = {
        "mode": cfg.mapper.mode,
        "world_frame": tiled.world_frame,
        "voxels": tiled.voxels,
        "tiles": len(tiled.tile_keys),
        "tasks": sorted(t for t in mine if t in finals),
        "missing": _missing(tasks, mine, finals, failed),
        **(metrics or {}),
        "config": to_dict(cfg),
    }
    (folder / "metrics.json").write_text(report_json(body))
    if tiled.voxels > options.max_merged_voxels:
        log.info("%s: %d voxels > %d: tiles only", folder, tiled.voxels, options.max_merged_voxels)
        return
    from tisem.merge_files import write_usual_files

    trajectories = [finals[t]["trajectory_xy"] for t in mine if t in finals]
    write_usual_files(
        folder,
        tiled.snapshot(),
        to_dict(cfg)["mapper"],
        {"world_frame": tiled.world_frame},
        trajectories,
    )


def _missing(tasks, mine, finals, failed) -> list[dict]:
    """What a group lacks: the scans of failed tasks, and the scans tasks skipped."""
    out = [
        {
            "task": t,
            "log": tasks[t].log.path,
            "first": tasks[t].first,
            "last": tasks[t].last if tasks[t].last < 1 << 62 else None,
            "reason": failed.get(t, "not run"),
        }
        for t in mine
        if t not in finals
    ]
    for t in mine:
        for s in (finals.get(t) or {}).get("skipped", []):
            out.append(
                {"task": t, "log": tasks[t].log.path, "scan": s["index"], "reason": s["reason"]}
            )
    losses = recording_losses({t: finals[t] for t in mine if t in finals})
    out += [
        {"task": t, "log": path, "lost": line} for path, lost in losses.items() for t, line in lost
    ]
    return out


def recording_losses(finals: dict[str, dict]) -> dict[str, list[tuple[str, str]]]:
    """log path -> [(task, line)] of what a damaged recording lost, each line once (with the
    first task that said it): every chunk of a log reads the same file and says so alike."""
    out: dict[str, list[tuple[str, str]]] = {}
    for t, summary in finals.items():
        lost = out.setdefault(summary["task"]["log"]["path"], [])
        said = {line for _, line in lost}
        lost += [(t, line) for line in summary.get("read_losses", []) if line not in said]
    return {path: lost for path, lost in out.items() if lost}


def fleet_report(
    options: FleetOptions,
    cfg: RunConfig,
    tasks: dict[str, MapTask],
    finals: dict[str, dict],
    failed: dict[str, str],
    maps: dict[str, Path],
    reduction: dict,
    metrics: dict,
    seconds: dict[str, float],
) -> dict:
    """fleet.json's content: the options, each task's summary, what failed or is missing,
    the merged maps, the reducers' reports, the metrics and each step's seconds."""
    return {
        "options": asdict(options),
        "mode": cfg.mapper.mode,
        "tasks": {
            t: {k: v for k, v in finals[t].items() if k != "trajectory_xy"} for t in sorted(finals)
        },
        "failed": dict(failed),
        "missing": [
            m for t in tasks if t not in finals for m in _missing(tasks, [t], finals, failed)
        ],
        "maps": {g: str(p) for g, p in maps.items()},
        "reduction": reduction,
        "metrics": metrics,
        "seconds": seconds,
    }


def report_json(data: dict) -> str:
    """A report as the fleet writes it: indented, paths and the like as strings."""
    return json.dumps(data, indent=1, default=str)
