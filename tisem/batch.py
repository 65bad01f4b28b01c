"""Batch runs and sweeps on Ray: every log under every config, one table at the end.

    result = run_batch(["/data/kitti/dataset"], "results/sweep",
                       sweeps=["mode=bki,st", "tau_s=2,5"], options=BatchOptions(threads=2))
    print(batch_table(result.rows))

A cell is one log mapped under one config: the base `overrides` plus one value of every
`--sweep key=v1,v2,...` (the cells are their product). Each cell is a mapping run
(`tisem.pipeline.run_pipeline`, final-map protocol) as a Ray task in its own process, into
`<out>/<log>/<cell>/` (config.yaml, metrics.json, predictions, map files), and writes
`cell.json` last: a cell with a `cell.json` for the same log and config is finished and is
kept, so a re-run does only what is missing (and starts no cluster when nothing is).
`batch.json` and the table hold every cell's metrics and seconds per scan.
"""

from __future__ import annotations

import itertools
import json
import logging
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from tisem import cluster
from tisem.config import load_config, to_dict
from tisem.errors import ConfigError
from tisem.logs import LogSpec, discover_logs, open_log, read_losses

log = logging.getLogger(__name__)

__all__ = [
    "BatchOptions",
    "BatchResult",
    "parse_sweeps",
    "plan_cells",
    "run_batch",
    "batch_table",
    "run_cell",
]

CELL_FILE = "cell.json"


@dataclass
class BatchOptions:
    threads: int = 2
    retries: int = 1
    address: str | None = None
    num_cpus: int | None = None
    arch: str = "cpu"
    map_files: bool = True
    progress: bool = True  # a bar counting the cells as they end


@dataclass
class BatchResult:
    out_dir: Path
    rows: list[dict]
    ran: int
    kept: int
    failed: dict[str, str] = field(default_factory=dict)


def parse_sweeps(sweeps: list[str]) -> list[tuple[str, list[str]]]:
    """['key=v1,v2', ...] -> [(key, [v1, v2]), ...]; a key swept twice is refused."""
    parsed: list[tuple[str, list[str]]] = []
    for text in sweeps:
        key, sep, values = text.partition("=")
        key = key.strip()
        choices = [v.strip() for v in values.split(",") if v.strip()]
        if not sep or not key or not choices:
            raise ValueError(f"--sweep expects key=v1,v2,..., got {text!r}")
        if key in (k for k, _ in parsed):
            raise ValueError(f"--sweep {key} given twice")
        parsed.append((key, choices))
    return parsed


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._=-]+", "_", text).strip("_")


def plan_cells(
    logs: list[LogSpec],
    overrides: list[str],
    sweeps: list[str],
    config_path: str | Path | None = None,
) -> list[dict]:
    """Every (log, config) cell: its name, folder name and overrides, each config checked."""
    parsed = parse_sweeps(sweeps)
    combos = list(itertools.product(*[[(k, v) for v in vs] for k, vs in parsed])) or [()]
    cells = []
    for combo in combos:
        assignments = [f"{k}={v}" for k, v in combo]
        name = ",".join(assignments) or "default"
        try:
            cfg = load_config(config_path, [*overrides, *assignments])  # bad keys fail here
        except ConfigError as exc:
            load_config(config_path, overrides)  # a --set's mistake is named as one
            raise ConfigError(str(exc).replace("--set", "--sweep", 1)) from None
        for spec in logs:
            cells.append(
                {
                    "log": spec.to_dict(),
                    "cell": name,
                    "folder": f"{spec.name}/{_slug(name)}",
                    "overrides": [*overrides, *assignments],
                    "config": to_dict(cfg),
                }
            )
    return cells


def _kept(folder: Path, cell: dict) -> dict | None:
    """The row an earlier run left for this cell (same log and config), or None."""
    path = folder / CELL_FILE
    if not path.is_file():
        return None
    try:
        saved = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    same = saved.get("log") == cell["log"] and saved.get("config") == cell["config"]
    return saved.get("row") if same else None


def run_cell(cell: dict, folder: str, threads: int, arch: str, map_files: bool) -> dict:
    """One cell's mapping run (in a process of its own: it starts Taichi); its table row."""
    from tisem.backend import init_taichi
    from tisem.config import run_config_from_dict
    from tisem.pipeline import run_pipeline

    cfg = run_config_from_dict(cell["config"])
    spec = LogSpec(**cell["log"])
    scans = open_log(spec, cfg.first, cfg.last, input=cfg.input, num_classes=cfg.mapper.num_classes)
    init_taichi(arch, threads=threads)
    started = time.perf_counter()
    result = run_pipeline(
        scans,
        cfg,
        folder,
        progress=False,
        write_outputs=map_files,
        sequence_name=spec.name,
        total=len(scans),
        source_info={
            "data" if spec.kind == "kitti" else "mcap": spec.path,
            **({"options": spec.options} if spec.kind == "mcap" else {}),
            "cell": cell["cell"],
            "threads": threads,
        },
    )
    m = result.metrics
    row = {
        "log": spec.name,
        "cell": cell["cell"],
        "scans": m["scans"],
        "skipped": len(m["skipped"]),
        "seconds_per_scan": m["seconds_per_scan"],
        "wall_seconds": time.perf_counter() - started,
        "evaluated": m["evaluated"],
        "read_losses": read_losses(scans),
        **{f"{k}": m["final"][k] for k in ("miou", "accuracy", "wiou")},
        "input_miou": m["input"]["miou"],
        "input_accuracy": m["input"]["accuracy"],
    }
    (Path(folder) / CELL_FILE).write_text(json.dumps({**cell, "row": row}, indent=1))
    return row


def run_batch(
    logs: list[LogSpec] | list[str],
    out_dir: str | Path,
    *,
    overrides: list[str] = (),
    sweeps: list[str] = (),
    options: BatchOptions | None = None,
    config_path: str | Path | None = None,
) -> BatchResult:
    """Run every missing cell (module docstring); write batch.json; return the rows.
    `config_path`: a YAML config under the overrides (default: the defaults)."""
    options = options or BatchOptions()
    out_dir = Path(out_dir).resolve()
    if logs and not isinstance(logs[0], LogSpec):
        logs = discover_logs([str(Path(p).resolve()) for p in logs])
    cells = plan_cells(list(logs), list(overrides), list(sweeps), config_path)
    rows: dict[str, dict] = {}
    todo = {}
    for cell in cells:
        kept = _kept(out_dir / cell["folder"], cell)
        if kept is not None:
            rows[cell["folder"]] = {**kept, "status": "kept"}
        else:
            todo[cell["folder"]] = cell
    failed: dict[str, str] = {}
    if todo:
        with cluster.ray_cluster(options.address, options.num_cpus):
            refs = {
                key: cluster.submit(
                    run_cell,
                    cpus=options.threads,
                    retries=options.retries,
                    args=(
                        cell,
                        str(out_dir / key),
                        options.threads,
                        options.arch,
                        options.map_files,
                    ),
                )
                for key, cell in todo.items()
            }
            done, failed = cluster.gather(refs, "cells" if options.progress else None)
        rows.update({key: {**row, "status": "ran"} for key, row in done.items()})
        for key, reason in failed.items():
            cell = todo[key]
            rows[key] = {
                "log": cell["log"]["name"],
                "cell": cell["cell"],
                "status": "failed",
                "reason": reason,
            }
    ordered = [rows[c["folder"]] for c in cells]
    ran = sum(r["status"] == "ran" for r in ordered)
    kept = sum(r["status"] == "kept" for r in ordered)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "batch.json").write_text(
        json.dumps(
            {
                "options": asdict(options),
                "overrides": list(overrides),
                "sweeps": list(sweeps),
                "cells": ordered,
                "ran": ran,
                "kept": kept,
                "failed": failed,
            },
            indent=1,
        )
    )
    return BatchResult(out_dir, ordered, ran, kept, failed)


def batch_table(rows: list[dict]) -> str:
    """A markdown table: one row per cell."""
    out = [
        "| log | cell | mIoU | accuracy | wIoU | network mIoU | s / scan | scans | status |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
    ]

    def num(r, k, fmt="{:.4f}"):
        v = r.get(k)
        return "–" if v is None else fmt.format(v)

    for r in rows:
        out.append(
            f"| {r['log']} | {r['cell']} | {num(r, 'miou')} | {num(r, 'accuracy')} | "
            f"{num(r, 'wiou')} | {num(r, 'input_miou')} | "
            f"{num(r, 'seconds_per_scan', '{:.3f}')} | {r.get('scans', '–')} | "
            f"{r['status']}{': ' + r['reason'] if r.get('reason') else ''} |"
        )
    return "\n".join(out)
