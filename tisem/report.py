"""What a finished run says: the metrics.json figures and the end-of-run table."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tisem.config import RunConfig, to_dict
from tisem.evaluate import Confusion, format_per_class, format_table
from tisem.progress import RunProgress, seconds_per_scan

if TYPE_CHECKING:
    from tisem.mapper import Mapper

__all__ = ["METRIC_KEYS", "run_metrics", "results_table", "aligned"]

# the figures of each protocol that metrics.json keeps
METRIC_KEYS = (
    "miou",
    "miou_all",
    "accuracy",
    "wiou",
    "oa_paper",
    "per_class_iou",
    "present_classes",
    "points",
)


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
        "seconds_per_scan": seconds_per_scan(seconds),
        "seconds_first_scan": float(seconds[0]) if seconds else None,
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


def _speed(metrics: dict) -> str:
    """The run's time per scan, the first scan's apart (metrics of older runs lack it)."""
    sps, first = metrics["seconds_per_scan"], metrics.get("seconds_first_scan")
    ms = f"{sps * 1000 if sps else float('nan'):.1f} ms per scan"
    if first is None:
        return f"{ms} (median)"
    if metrics["scans"] < 2:
        return f"{ms} (its only scan, which loads the kernels)"
    return f"{ms} (median after the first, which took {first * 1000:.0f} ms: it loads the kernels)"


def aligned(table: str) -> str:
    """A markdown table with its columns padded to one width, so that it reads as a table in a
    terminal and stays valid markdown (numbers right-aligned, as the `---:` rule says). Lines
    that are not table rows (a footnote) are kept as they are."""
    lines = table.splitlines()
    rows = {
        i: [cell.strip() for cell in line.strip().strip("|").split(" | ")]
        for i, line in enumerate(lines)
        if line.startswith("|")
    }
    if not rows:
        return table
    columns = max(len(row) for row in rows.values())
    widths = [max(len(row[c]) for row in rows.values() if c < len(row)) for c in range(columns)]
    for i, row in rows.items():
        cells = []
        for c, cell in enumerate(row):
            if cell and set(cell) <= set("-:"):  # the header rule
                cells.append("-" * (widths[c] - 1) + ":" if cell.endswith(":") else "-" * widths[c])
            else:
                cells.append(cell.ljust(widths[c]) if c == 0 else cell.rjust(widths[c]))
        lines[i] = "| " + " | ".join(cells) + " |"
    return "\n".join(lines)


def results_table(metrics: dict, per_class: bool = False, input_name: str = "network input") -> str:
    """The end-of-run table: the input (`input_name`: the network's labels, or the ground truth
    given as input) vs the map, both protocols, with `per_class` the IoU of every class, then
    a summary (scans mapped and skipped, time per scan, voxels; the points left unmapped by
    the height band and by the range band, counted apart)."""
    rows = []
    if metrics["evaluated"]:
        mode = metrics["mode"]
        rows = [
            (input_name, metrics["input"]),
            (f"map, final ({mode})", metrics["final"]),
            (f"map, online ({mode})", metrics["online"]),
        ]
    text = aligned(format_table(rows)) if rows else "(no ground truth: nothing to score)"
    if rows and per_class:
        # metrics of a run resumed from an older checkpoint may lack the present classes: then
        # every class with a defined IoU counts as present (none is marked)
        shown = [
            (
                name,
                {
                    "present_classes": [c for c, v in m["per_class_iou"].items() if v is not None],
                    **m,
                },
            )
            for name, m in rows
        ]
        text += "\n\nIoU per class\n" + aligned(format_per_class(shown))
    text += (
        f"\n\n{metrics['scans']} scans mapped, {len(metrics['skipped'])} skipped; "
        f"{_speed(metrics)}; {metrics['active_voxels']:,} voxels"
    )
    dropped = metrics.get("dropped") or {}
    band, out_of_range = dropped.get("dropped_band", 0), dropped.get("dropped_range", 0)
    text += (
        f"\nunmapped points: {band:,} outside the height band, {out_of_range:,} outside "
        f"the range band"
    )
    relabelled = metrics.get("relabelled")  # (metrics of older runs lack it)
    unknown = dropped.get("unknown_raw_ids", 0)
    if unknown and relabelled and relabelled["points"]:
        # labels the label space has no class for (a wrong --classes or label space) or no
        # label at all: a run must not pass over them in the per-scan lines only
        points = relabelled["points"] + dropped.get("dropped_nonfinite", 0)
        text += (
            f"\ninput labels with no class: {unknown:,} ({100 * unknown / points:.2f} % of the "
            f"points), no evidence: ids the label space (--classes) does not name, or values "
            f"that are no label"
        )
    if relabelled and relabelled["points"]:
        text += (
            f"\nthe final map changed the input's label at {relabelled['changed']:,} of "
            f"{relabelled['points']:,} points ({100 * relabelled['share']:.2f} %)"
        )
    return text
