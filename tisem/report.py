"""What a finished run says: the metrics.json figures and the end-of-run table."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tisem.config import RunConfig, to_dict
from tisem.evaluate import Confusion, format_per_class, format_table
from tisem.progress import RunProgress

if TYPE_CHECKING:
    from tisem.mapper import Mapper

__all__ = ["METRIC_KEYS", "run_metrics", "results_table", "aligned"]

# the figures of each protocol that metrics.json keeps
METRIC_KEYS = ("miou", "miou_all", "accuracy", "wiou", "oa_paper", "per_class_iou", "points")


def _summary(conf: Confusion) -> dict:
    m = conf.metrics()
    return {k: m[k] for k in METRIC_KEYS}


def run_metrics(progress: RunProgress, final: Confusion, mapper: Mapper, cfg: RunConfig) -> dict:
    """metrics.json: the three protocols (final map, online, network input), timings, voxel
    counts, skipped scans, dropped points and the resolved config."""
    seconds = progress.seconds
    return {
        "mode": cfg.mapper.mode,
        "scans": progress.mapped,
        "skipped": [vars(s) for s in progress.skipped],
        "seconds_per_scan": float(np.median(seconds)) if seconds else None,
        "seconds_total": float(np.sum(seconds)),
        "active_voxels": mapper.live_voxels + mapper.stored_voxels,
        "live_voxels": mapper.live_voxels,
        "stored_voxels": mapper.stored_voxels,
        "dropped": progress.drops.totals,
        "dropped_scans": progress.drops.scans,
        "evaluated": final.metrics()["points"] > 0,
        "final": _summary(final),
        "online": _summary(progress.online),
        "input": _summary(progress.input),
        "config": to_dict(cfg),
    }


def aligned(table: str) -> str:
    """A markdown table with its columns padded to one width, so that it reads as a table in a
    terminal and stays valid markdown (numbers right-aligned, as the `---:` rule says)."""
    rows = [[cell.strip() for cell in line.strip().strip("|").split(" | ")]
            for line in table.splitlines()]
    widths = [max(len(row[i]) for row in rows if i < len(row)) for i in range(len(rows[0]))]
    lines = []
    for row in rows:
        cells = []
        for i, cell in enumerate(row):
            if set(cell) <= set("-:"):                        # the header rule
                cells.append("-" * (widths[i] - 1) + ":" if cell.endswith(":")
                             else "-" * widths[i])
            else:
                cells.append(cell.ljust(widths[i]) if i == 0 else cell.rjust(widths[i]))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def results_table(metrics: dict, per_class: bool = False, input_name: str = "network input"
                  ) -> str:
    """The end-of-run table: the input (`input_name`: the network's labels, or the ground truth
    given as input) vs the map, both protocols, with `per_class` the IoU of every class, then
    one summary line (scans mapped and skipped, time per scan, voxels)."""
    rows = []
    if metrics["evaluated"]:
        mode = metrics["mode"]
        rows = [(input_name, metrics["input"]), (f"map, final ({mode})", metrics["final"]),
                (f"map, online ({mode})", metrics["online"])]
    text = aligned(format_table(rows)) if rows else "(no ground truth: nothing to score)"
    if rows and per_class:
        # metrics.json keeps no list of the classes present in the ground truth: every class
        # with a defined IoU is shown (0 for one that is predicted but not in the ground truth)
        shown = [(name, {**m, "present_classes": [c for c, v in m["per_class_iou"].items()
                                                  if v is not None]}) for name, m in rows]
        text += "\n\nIoU per class\n" + aligned(format_per_class(shown))
    sps = metrics["seconds_per_scan"]
    text += (f"\n\n{metrics['scans']} scans mapped, {len(metrics['skipped'])} skipped; "
             f"{sps * 1000 if sps else float('nan'):.1f} ms per scan (median); "
             f"{metrics['active_voxels']:,} voxels")
    return text
