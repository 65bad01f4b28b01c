"""A stream of scans through the mapper: progress, evaluation, results folder.

    result = run_pipeline(SemanticKittiSequence(path), load_config(), "results/run")

Writes `config.yaml`, `run.json`, `metrics.json`, per-point predictions in SemanticKITTI layout
(`sequences/NN/predictions/NNNNNN.label`, final-map protocol) and the map files, and prints a
table of the metrics. Bad scans arrive as `SkippedScan`s: they are reported, the rest is mapped.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np
import taichi as ti
from tqdm import tqdm

from tisem.config import RunConfig, save_config, to_dict
from tisem.errors import ScanError, SkippedScan
from tisem.evaluate import Confusion, format_table
from tisem.io.semantickitti import write_predictions
from tisem.mapper import Mapper
from tisem.scan import Scan, finite_rows

log = logging.getLogger(__name__)

METRIC_KEYS = ("miou", "miou_all", "accuracy", "wiou", "oa_paper", "per_class_iou", "points")


@dataclass
class RunResult:
    metrics: dict
    mapper: Mapper
    out_dir: Path
    skipped: list[SkippedScan] = field(default_factory=list)
    trajectory: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


class DropLog:
    """Points a mapped scan lost, and why: logged per scan (when it is more than the routine
    range filter) and totalled for metrics.json."""

    ANOMALIES = {"dropped_nonfinite": "non-finite (NaN/inf) points",
                 "unknown_raw_ids": "unknown raw ids (mapped to 0)",
                 "dropped_far": "implausibly far points (> 1 km)",
                 "dropped_window": "points outside the map's index window"}

    def __init__(self):
        self.totals = {k: 0 for k in ("dropped_nonfinite", "unknown_raw_ids", "dropped_range",
                                      "dropped_far", "dropped_window")}
        self.scans: list[dict] = []

    def to_dict(self) -> dict:
        return {"totals": dict(self.totals), "scans": list(self.scans)}

    def restore(self, saved: dict) -> None:
        """Continue from a checkpoint's `to_dict()`."""
        for k, v in saved.get("totals", {}).items():
            self.totals[k] = self.totals.get(k, 0) + int(v)
        self.scans[:0] = saved.get("scans", [])

    def add(self, scan: Scan, report) -> None:
        counts = {"dropped_nonfinite": report.dropped_nonfinite,
                  "unknown_raw_ids": scan.source.unknown_raw_ids if scan.source else 0,
                  "dropped_range": report.dropped_range, "dropped_far": report.dropped_far,
                  "dropped_window": report.dropped_window}
        for k, v in counts.items():
            self.totals[k] += int(v)
        anomalies = {k: int(counts[k]) for k in self.ANOMALIES if counts[k]}
        if anomalies:
            self.scans.append({"index": scan.index, "name": scan.name, **anomalies})
            log.info("scan %s (%s): %s", scan.index, scan.name,
                     ", ".join(f"{v} {self.ANOMALIES[k]}" for k, v in anomalies.items()))


def _input_labels(scan: Scan) -> np.ndarray:
    """The network's own per-point answer, scored like the map (probabilities -> argmax)."""
    if scan.labels is not None:
        return scan.labels
    lab = np.argmax(scan.probs, axis=1).astype(np.int32)
    lab[scan.probs.sum(axis=1) <= 0] = 0
    return lab


def _score(conf: Confusion, scan: Scan, labels: np.ndarray) -> None:
    """Add a scan's answers to a confusion; non-finite points are no measurement: not scored."""
    ok = finite_rows(scan.points_sensor)
    if ok.all():
        conf.add(scan.gt_labels, labels)
    else:
        conf.add(scan.gt_labels[ok], labels[ok])


def _reiterable(scans: Iterable) -> bool:
    return iter(scans) is not scans


def _summary(conf: Confusion) -> dict:
    m = conf.metrics()
    return {k: m[k] for k in METRIC_KEYS}


def run_pipeline(scans: Iterable[Scan | SkippedScan], cfg: RunConfig, out_dir: str | Path, *,
                 sequence_name: str = "00", total: int | None = None, progress: bool = True,
                 source_info: dict | None = None, mapper: Mapper | None = None,
                 on_scan=None, write_outputs: bool = True, checkpoint_every: int = 0,
                 checkpoint_dir: str | Path | None = None, resume=None) -> RunResult:
    """Map every scan, then score and write everything (see module docstring).

    `scans` may be any iterable; when it can be iterated twice (a sequence object), the
    final-map pass reads the scans again instead of keeping them in memory.
    `on_scan(mapper, scan, k)` is called after each integrated scan.
    `checkpoint_every=N` saves the map and the metrics so far every N mapped scans, atomically,
    to `checkpoint_dir` (default `<out_dir>/checkpoint/`). `resume` (a results folder, its
    checkpoint folder or file, or a `tisem.checkpoint.Checkpoint`) continues such a run: the
    mapper comes from the checkpoint, scans with index <= its last integrated one are passed
    over (not integrated again), and the metrics go on from the stored ones.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out_dir / "config.yaml")
    info = dict(source_info or {}, sequence=sequence_name)
    (out_dir / "run.json").write_text(json.dumps(info, indent=2, default=str))

    ckpt = None
    if resume is not None:
        from tisem.checkpoint import open_checkpoint
        if mapper is not None:
            raise ValueError("give either mapper= or resume=, not both")
        ckpt = open_checkpoint(resume)
        ckpt.check_run_config(cfg)
        mapper = ckpt.build_mapper(store_dir=cfg.mapper.store_dir)
    mapper = mapper or Mapper(cfg.mapper)
    drops = DropLog()
    online, input_conf = Confusion(mapper.C), Confusion(mapper.C)
    seconds, skipped, trajectory, kept = [], [], [], []
    done_upto = None   # scans with index <= this were integrated before the checkpoint
    if ckpt is not None:
        ckpt.restore_progress(online, input_conf, seconds, skipped, trajectory, drops)
        done_upto = ckpt.last_index
        log.info("resuming from %s: %d scans mapped, up to scan %s", ckpt.path, len(seconds),
                 done_upto)
    refused = {s.index for s in skipped}
    ckpt_dir = Path(checkpoint_dir) if checkpoint_dir is not None else out_dir / "checkpoint"
    keep_in_memory = not _reiterable(scans)
    bar = tqdm(scans, total=total, unit="scan", desc=f"mapping ({cfg.mapper.mode})",
               disable=not progress)
    for k, item in enumerate(bar):
        if done_upto is not None and item.index <= done_upto:
            if keep_in_memory and not isinstance(item, SkippedScan) and item.index not in refused:
                kept.append(item)   # still needed by the final-map pass
            continue
        if isinstance(item, SkippedScan):
            skipped.append(item)
            log.warning("skipped scan %s (%s): %s", item.index, item.name, item.reason)
            continue
        try:
            ti.sync()
            start = time.perf_counter()
            report = mapper.integrate(item)
            ti.sync()
            seconds.append(time.perf_counter() - start)
            drops.add(item, report)
        except ValueError as exc:   # a scan the mapper refuses (bad labels, pose far away, ...)
            skipped.append(SkippedScan(item.index, item.name, str(exc)))
            log.warning("skipped scan %s: %s", item.index, exc)
            continue
        trajectory.append(item.T_world_sensor[:3, 3])
        if item.gt_labels is not None:
            _score(input_conf, item, _input_labels(item))
            if cfg.online_eval:
                labels, _ = mapper.query(item.points_world(), with_probs=False)
                _score(online, item, labels)
        if keep_in_memory:
            kept.append(item)
        if on_scan is not None:
            on_scan(mapper, item, k)
        if checkpoint_every and len(seconds) % checkpoint_every == 0:
            from tisem.checkpoint import save_checkpoint
            save_checkpoint(ckpt_dir, mapper, last_index=item.index, run_config=cfg,
                            online=online, input_conf=input_conf, seconds=seconds,
                            skipped=skipped, trajectory=trajectory, source=info, drops=drops)
        bar.set_postfix(voxels=f"{mapper.live_voxels / 1e3:.0f}k", refresh=False)

    # final-map protocol: every scan looked up in the finished map
    final = Confusion(mapper.C)
    pred_root = out_dir
    for item in (kept if keep_in_memory else scans):
        if isinstance(item, SkippedScan):
            continue
        labels, _ = mapper.query(item.points_world(), with_probs=False)
        write_predictions(pred_root, sequence_name, item.index, labels)
        if item.gt_labels is not None:
            _score(final, item, labels)

    mapped = len(seconds)
    metrics = {
        "mode": cfg.mapper.mode,
        "scans": mapped,
        "skipped": [vars(s) for s in skipped],
        "seconds_per_scan": float(np.median(seconds)) if seconds else None,
        "seconds_total": float(np.sum(seconds)),
        "active_voxels": mapper.live_voxels + mapper.stored_voxels,
        "live_voxels": mapper.live_voxels,
        "stored_voxels": mapper.stored_voxels,
        "dropped": drops.totals,
        "dropped_scans": drops.scans,
        "evaluated": final.metrics()["points"] > 0,
        "final": _summary(final),
        "online": _summary(online),
        "input": _summary(input_conf),
        "config": to_dict(cfg),
    }
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    result = RunResult(metrics, mapper, out_dir, skipped, np.array(trajectory).reshape(-1, 3))
    if write_outputs:
        from tisem.outputs import write_map_files
        write_map_files(result, cfg)
    return result


def results_table(metrics: dict) -> str:
    """The end-of-run table: input vs map, both protocols."""
    rows = []
    if metrics["evaluated"]:
        rows = [("network input", metrics["input"]), (f"map, final ({metrics['mode']})", metrics["final"]),
                (f"map, online ({metrics['mode']})", metrics["online"])]
    text = format_table(rows) if rows else "(no ground truth: nothing to score)"
    sps = metrics["seconds_per_scan"]
    text += (f"\n\n{metrics['scans']} scans mapped, {len(metrics['skipped'])} skipped; "
             f"{sps * 1000 if sps else float('nan'):.1f} ms per scan (median); "
             f"{metrics['active_voxels']:,} voxels")
    return text
