"""Side-by-side comparison of a region: raw network labels | the map's labels | ground truth.

Reads a results folder written by the pipeline (`run.json`, `config.yaml`, the map's per-point
predictions in `sequences/NN/predictions/`) and the input it names (a SemanticKITTI sequence or
an MCAP recording: `tisem.viz.sources`), and draws the
points of a region top-down with the same raster as the BEV (highest point per cell), so the
three panels differ only by their labels and the map's cleaning shows as colour changes.
Each panel's title carries its accuracy against the ground truth over the region's points.
Without ground truth the third panel draws the points whose map label is not the network's,
in the map's class: where the map overruled the network, which a user can check by eye.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import yaml
from matplotlib.figure import Figure

from tisem.labels import raw_to_train
from tisem.viz.bev import (
    TopDownGrid,
    add_scale_bar,
    draw_label_image,
    draw_trajectory,
    legend_handles,
    top_labels,
)
from tisem.viz.sources import open_run_scans

__all__ = ["render_comparison", "load_results", "region_accuracy", "DEFAULT_REGION_M"]

DEFAULT_REGION_M = 40.0  # side of the default square region
_PANEL_PX = 400  # cells across a panel (0.1 m for the default region)
_DEFAULT_MAX_RANGE_M = 80.0  # scans whose sensor is farther than this from the region are skipped


def load_results(results_dir: str | os.PathLike) -> tuple[dict, dict]:
    """(run.json, config.yaml) of a results folder, with errors that name the missing file."""
    results_dir = Path(results_dir)
    run_path = results_dir / "run.json"
    if not run_path.is_file():
        raise FileNotFoundError(f"{run_path}: not found; is {results_dir} a tisem results folder?")
    with open(run_path) as f:
        run = json.load(f)
    config_path = results_dir / "config.yaml"
    config = {}
    if config_path.is_file():
        with open(config_path) as f:
            config = yaml.safe_load(f) or {}
    return run, config


def region_accuracy(pred: np.ndarray, gt: np.ndarray) -> tuple[float | None, int]:
    """(accuracy, evaluated points) by the evaluation's rules (`tisem.evaluate`): GT 0 is
    ignored, a prediction of 0 is wrong."""
    valid = gt != 0
    n = int(np.count_nonzero(valid))
    return (float(np.mean(pred[valid] == gt[valid])) if n else None), n


def _map_predictions_dir(results_dir: Path, sequence_name: str) -> Path:
    folder = results_dir / "sequences" / sequence_name / "predictions"
    if folder.is_dir():
        return folder
    found = sorted((results_dir / "sequences").glob("*/predictions"))
    if len(found) == 1:
        return found[0]
    raise FileNotFoundError(f"{folder}: the map's per-point predictions are missing")


def _map_labels(path: Path, scan) -> np.ndarray | None:
    """The map's train ids for `scan`'s points (one per point of the scan file, as the
    pipeline writes them), or None when the file is missing or has another length."""
    if not path.is_file():
        return None
    raw = np.fromfile(path, dtype="<u4")
    if raw.size != scan.num_points:
        return None
    return raw_to_train(raw)[0]


def _region_around(xy: np.ndarray, size_m: float) -> tuple[float, float, float, float]:
    h = size_m / 2.0
    return (float(xy[0] - h), float(xy[1] - h), float(xy[0] + h), float(xy[1] + h))


def _distance_to_box(xy: np.ndarray, box) -> np.ndarray:
    x0, y0, x1, y1 = box
    dx = np.maximum(0.0, np.maximum(x0 - xy[:, 0], xy[:, 0] - x1))
    dy = np.maximum(0.0, np.maximum(y0 - xy[:, 1], xy[:, 1] - y1))
    return np.hypot(dx, dy)


def render_comparison(
    results_dir: str | os.PathLike,
    out: str | os.PathLike | None = None,
    region=None,
    scan: int | None = None,
    pixel_m: float | None = None,
) -> dict:
    """Draw the 3-panel comparison PNG; returns {"out", "region", "scans", "points", "accuracy"}.

    region: (x0, y0, x1, y1) world metres; default a 40 m square around the middle of the
        trajectory (or around the sensor of `scan`).
    scan: a scan id to draw alone; default every scan of the run whose sensor is within the
        mapper's max range of the region.
    out: default `results_dir/compare.png` (`compare_NNNNNN.png` with `scan`).
    """
    results_dir = Path(results_dir)
    run, config = load_results(results_dir)
    seq = open_run_scans(run, config, results_dir, results_dir / "run.json")
    input_title = seq.input_title
    pred_dir = _map_predictions_dir(results_dir, seq.sequence_name)

    run_ids = set(int(i) for i in run.get("scan_ids", seq.scan_ids))
    positions = {
        k: seq.poses_lidar[k][:3, 3]
        for k, sid in enumerate(seq.scan_ids)
        if sid in run_ids and seq.has_pose[k]
    }
    if not positions:
        raise ValueError(f"{results_dir}: no scan of the run has a pose in {seq.origin}")
    trajectory = np.array([positions[k][:2] for k in sorted(positions)])
    if scan is not None:
        chosen = [k for k in positions if seq.scan_ids[k] == int(scan)]
        if not chosen:
            raise ValueError(
                f"scan {scan} is not a mapped scan of {results_dir} "
                f"(scans {min(run_ids)}..{max(run_ids)})"
            )
    else:
        chosen = sorted(positions)
    if region is None:
        centre = positions[chosen[0]] if scan is not None else trajectory[len(trajectory) // 2]
        region = _region_around(np.asarray(centre[:2]), DEFAULT_REGION_M)
    x0, y0, x1, y1 = (float(v) for v in region)
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"region must be x0 y0 x1 y1 with x1 > x0 and y1 > y0, got {region}")
    reach = float((config.get("mapper") or {}).get("max_range_m", _DEFAULT_MAX_RANGE_M))
    sensor_xy = np.array([positions[k][:2] for k in chosen])
    chosen = [
        k for k, d in zip(chosen, _distance_to_box(sensor_xy, (x0, y0, x1, y1))) if d <= reach
    ]

    # gather the region's points with their three labelings
    parts = {"xy": [], "z": [], "net": [], "map": [], "gt": []}
    used, skipped = [], []
    for _k, s in seq.load(chosen):
        if isinstance(s, str):  # why the scan cannot be read
            skipped.append(s)
            continue
        mapped = _map_labels(pred_dir / f"{s.index:06d}.label", s)
        if mapped is None:
            skipped.append(f"{s.index}: no matching map predictions in {pred_dir}")
            continue
        pts = s.points_world()
        inside = (pts[:, 0] >= x0) & (pts[:, 0] < x1) & (pts[:, 1] >= y0) & (pts[:, 1] < y1)
        gt = s.gt_labels if s.gt_labels is not None else np.zeros(s.num_points, np.int32)
        for key, values in (
            ("xy", pts[:, :2]),
            ("z", pts[:, 2]),
            ("net", s.labels),
            ("map", mapped),
            ("gt", gt),
        ):
            parts[key].append(values[inside])
        used.append(s.index)
    if not used:
        raise ValueError(
            f"{results_dir}: no scan could be drawn for region {region}: "
            + ("; ".join(skipped) or "no scan within reach")
        )
    pts = {key: np.concatenate(v) for key, v in parts.items()}
    has_gt = seq.has_ground_truth

    cell = float(pixel_m) if pixel_m else max(x1 - x0, y1 - y0) / _PANEL_PX
    grid = TopDownGrid.covering(x0, y0, x1, y1, cell)
    accuracy = {
        "network": region_accuracy(pts["net"], pts["gt"])[0] if has_gt else None,
        "map": region_accuracy(pts["map"], pts["gt"])[0] if has_gt else None,
    }
    n_eval = region_accuracy(pts["map"], pts["gt"])[1]

    def acc_text(a):
        return "accuracy n/a (no ground truth)" if a is None else f"accuracy {100 * a:.2f} %"

    everywhere = slice(None)  # (a view: the panels of every point copy nothing)
    changed = pts["map"] != pts["net"]
    panels = [
        (input_title, pts["net"], everywhere, acc_text(accuracy["network"])),
        ("map", pts["map"], everywhere, acc_text(accuracy["map"])),
    ]
    if has_gt:
        panels.append(("ground truth", pts["gt"], everywhere, f"{n_eval} labelled points"))
    else:  # what a user without ground truth can check: where the map overruled the network
        share = 100 * changed.mean() if len(changed) else 0.0
        panels.append(
            (
                "where the map changed the network's label (no ground truth)",
                pts["map"],
                changed,
                f"{int(changed.sum())} points ({share:.2f} %), in the map's class",
            )
        )
    fig = Figure(figsize=(18, 7.4), dpi=100, layout="constrained", facecolor="white")
    axes = fig.subplots(1, 3, sharex=True, sharey=True)
    present = set()
    for ax, (name, labels, drawn, subtitle) in zip(axes, panels):
        image = top_labels(grid, pts["xy"][drawn], pts["z"][drawn], labels[drawn])
        present.update(np.unique(image[image >= 0]).tolist())
        draw_label_image(ax, grid, image)
        draw_trajectory(ax, trajectory)
        ax.set_xlim(x0, x1)  # the trajectory must not widen the view
        ax.set_ylim(y0, y1)
        ax.set_title(f"{name}\n{subtitle}", fontsize=12)
        ax.set_xlabel("x [m]")
    axes[0].set_ylabel("y [m]")
    add_scale_bar(axes[0], x1 - x0)
    ids = f"{used[0]}" if len(used) == 1 else f"{min(used)}..{max(used)} ({len(used)})"
    fig.suptitle(
        f"{results_dir.name}: sequence {seq.sequence_name}, scans {ids}, region "
        f"x {x0:.1f}..{x1:.1f} m, y {y0:.1f}..{y1:.1f} m, {len(pts['z'])} points, "
        f"cell {grid.pixel_m:.2g} m",
        fontsize=12,
    )
    handles = legend_handles(present)
    if handles:
        fig.legend(
            handles=handles,
            loc="outside lower center",
            ncols=min(10, len(handles)),
            frameon=False,
            fontsize=10,
        )
    if out is None:
        out = results_dir / ("compare.png" if scan is None else f"compare_{int(scan):06d}.png")
    fig.savefig(os.fspath(out), format="png")
    return {
        "out": Path(out),
        "region": (x0, y0, x1, y1),
        "scans": used,
        "skipped": skipped,
        "points": int(len(pts["z"])),
        "evaluated": n_eval,
        "accuracy": accuracy,
        "changed": int(changed.sum()),  # points whose map label is not the network's
    }
