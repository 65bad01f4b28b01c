"""A mapping run: a stream of scans through the mapper, then the final map scored and written.

    result = MappingRun(SemanticKittiSequence(path), load_config(), "results/run").run()
    result = MappingRun.resume(SemanticKittiSequence(path), "results/run").run()  # after a crash

The steps, in order: write config.yaml and run.json; map every scan (scoring the network's
labels and, with `online_eval`, the map right after the scan), saving a checkpoint every N
mapped scans; look every scan up in the finished map (the final-map protocol), writing its
per-point predictions in SemanticKITTI layout; write metrics.json; write the map files.
Bad scans arrive as `SkippedScan`s, or the mapper refuses them: each is logged once and
listed in metrics.json, and the rest is mapped.
"""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import taichi as ti
from tqdm import tqdm

from tisem import outputs
from tisem.checkpoint import CHECKPOINT_DIR, Checkpoint, open_checkpoint, save_checkpoint
from tisem.config import RunConfig
from tisem.errors import SkippedScan
from tisem.evaluate import Confusion, network_labels, score_scan
from tisem.io.semantickitti import write_predictions
from tisem.mapper import Mapper
from tisem.progress import RunProgress
from tisem.report import run_metrics
from tisem.scan import Scan

log = logging.getLogger(__name__)

__all__ = ["MappingRun", "RunResult"]

OnScan = Callable[[Mapper, Scan, int], None]


@dataclass
class RunResult:
    """A finished run: its metrics.json, the mapper holding the final map, where it wrote."""

    metrics: dict
    mapper: Mapper
    out_dir: Path
    skipped: list[SkippedScan] = field(default_factory=list)
    trajectory: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


class MappingRun:
    """One run over `scans` (any iterable of `Scan | SkippedScan`) into `out_dir`.

    When `scans` can be iterated twice (a sequence object), the final-map pass reads the scans
    again instead of keeping them in memory. `sequence_name` names the predictions folder
    (`sequences/NN/`), `total` sizes the progress bar, `source_info` goes into run.json (what
    was read). `checkpoint_every=N` saves the map and the progress every N mapped scans,
    atomically, to `checkpoint_dir` (default `<out_dir>/checkpoint/`). `mapper` and
    `progress` start the run from a map and a progress other than empty ones (`resume` builds
    both from a checkpoint); scans with `Scan.index <= progress.last_index` are then passed over.
    """

    def __init__(self, scans: Iterable[Scan | SkippedScan], cfg: RunConfig,
                 out_dir: str | os.PathLike, *, sequence_name: str = "00",
                 total: int | None = None, source_info: dict | None = None,
                 checkpoint_every: int = 0, checkpoint_dir: str | os.PathLike | None = None,
                 mapper: Mapper | None = None, progress: RunProgress | None = None):
        self.scans = scans
        self.cfg = cfg
        self.out_dir = Path(out_dir)
        self.sequence_name = sequence_name
        self.total = total
        self.checkpoint_every = int(checkpoint_every or 0)
        self.checkpoint_dir = (Path(checkpoint_dir) if checkpoint_dir is not None
                               else self.out_dir / CHECKPOINT_DIR)
        # run.json; a resumed run finds its checkpoint cadence there
        self.info = dict(source_info or {}, checkpoint_every=self.checkpoint_every,
                         sequence=sequence_name)
        self.mapper = mapper or Mapper(cfg.mapper)
        self.progress = progress or RunProgress.start(self.mapper.C)

    @classmethod
    def resume(cls, scans: Iterable[Scan | SkippedScan], checkpoint: Checkpoint | str | os.PathLike,
               cfg: RunConfig | None = None, out_dir: str | os.PathLike | None = None, *,
               sequence_name: str | None = None, source_info: dict | None = None,
               checkpoint_every: int | None = None, **options) -> MappingRun:
        """The run a checkpoint (a `Checkpoint`, a results folder, its checkpoint folder or
        the file) belongs to, ready to go on: its map, its progress, and unless given, its
        config, results folder, sequence name, run.json and checkpoint cadence. `scans` is the
        whole stream again; what the checkpoint holds is passed over. A `cfg` whose mapper
        config differs from the checkpoint's is refused (ValueError) before any map is built.
        """
        ckpt = open_checkpoint(checkpoint)
        cfg = cfg if cfg is not None else ckpt.run_config()
        ckpt.check_run_config(cfg)
        source = ckpt.source
        mapper = ckpt.build_mapper(store_dir=cfg.mapper.store_dir)
        progress = ckpt.progress(mapper.C)
        log.info("resuming from %s: %d scans mapped, up to scan %s", ckpt.path, progress.mapped,
                 progress.last_index)
        if source_info is None:
            source_info = {k: v for k, v in source.items()
                           if k not in ("sequence", "checkpoint_every")}
        return cls(scans, cfg, out_dir if out_dir is not None else ckpt.results_dir,
                   sequence_name=sequence_name or source.get("sequence", "00"),
                   source_info=source_info,
                   checkpoint_every=(checkpoint_every if checkpoint_every is not None
                                     else source.get("checkpoint_every", 0)),
                   mapper=mapper, progress=progress, **options)

    # ------------------------------------------------------------------ the steps
    def run(self, *, show_progress: bool = True, on_scan: OnScan | None = None,
            write_map_files: bool = True) -> RunResult:
        """Every step (module docstring); `on_scan(mapper, scan, k)` is called after each
        integrated scan (k: its position in the stream)."""
        outputs.write_run_info(self.out_dir, self.cfg, self.info)
        final_scans = self.map_scans(show_progress, on_scan)
        final = self.final_pass(final_scans)
        metrics = run_metrics(self.progress, final, self.mapper, self.cfg)
        outputs.write_metrics(self.out_dir, metrics)
        result = RunResult(metrics, self.mapper, self.out_dir, list(self.progress.skipped),
                           self.progress.trajectory_array())
        if write_map_files:
            outputs.write_map_files(self.out_dir, self.mapper, self.cfg.mapper,
                                    result.trajectory)
        return result

    def map_scans(self, show_progress: bool = True,
                  on_scan: OnScan | None = None) -> Iterable[Scan | SkippedScan]:
        """Integrate every scan not integrated before; returns the scans for the final pass
        (the stream itself when it can be read again, else the scans kept in memory)."""
        progress = self.progress
        done_upto = progress.last_index
        keep_in_memory = iter(self.scans) is self.scans       # an iterator: read once
        kept: list[Scan] = []
        bar = tqdm(self.scans, total=self.total, unit="scan",
                   desc=f"mapping ({self.cfg.mapper.mode})", disable=not show_progress)
        for k, item in enumerate(bar):
            if done_upto is not None and item.index <= done_upto:
                # in the checkpoint already; the final pass still needs what was mapped
                if (keep_in_memory and not isinstance(item, SkippedScan)
                        and not progress.was_skipped(item.index)):
                    kept.append(item)
                continue
            if isinstance(item, SkippedScan):
                self._skip(item)
                continue
            if not self._integrate(item):
                continue
            if keep_in_memory:
                kept.append(item)
            if on_scan is not None:
                on_scan(self.mapper, item, k)
            if self.checkpoint_every and progress.mapped % self.checkpoint_every == 0:
                self.write_checkpoint()
            bar.set_postfix(voxels=f"{self.mapper.live_voxels / 1e3:.0f}k", refresh=False)
        return kept if keep_in_memory else self.scans

    def _integrate(self, scan: Scan) -> bool:
        """Map one scan and score it; False when the mapper refused it (it is skipped)."""
        try:
            ti.sync()
            start = time.perf_counter()
            report = self.mapper.integrate(scan)
            ti.sync()
            seconds = time.perf_counter() - start
        except ValueError as exc:   # a scan the mapper refuses (bad labels, pose far away, ...)
            self._skip(SkippedScan(scan.index, scan.name, str(exc)))
            return False
        self.progress.add_mapped(scan, seconds, report)
        if scan.gt_labels is not None:
            score_scan(self.progress.input, scan, network_labels(scan))
            if self.cfg.online_eval:
                labels, _ = self.mapper.query(scan.points_world(), with_probs=False)
                score_scan(self.progress.online, scan, labels)
        return True

    def _skip(self, skipped: SkippedScan) -> None:
        """The one place a skipped scan is reported: one line as it happens (the end-of-run
        table counts them, metrics.json lists them)."""
        self.progress.add_skipped(skipped)
        log.warning("skipped scan %s (%s): %s", skipped.index, skipped.name, skipped.reason)

    def write_checkpoint(self) -> Path:
        """The map and the progress so far, to `checkpoint_dir` (atomically)."""
        return save_checkpoint(self.checkpoint_dir, self.mapper, self.progress,
                               run_config=self.cfg, source=self.info)

    def final_pass(self, scans: Iterable[Scan | SkippedScan]) -> Confusion:
        """The final-map protocol: every scan looked up in the finished map; writes its
        predictions (one label per point of the scan) and returns the pooled confusion."""
        final = Confusion(self.mapper.C)
        for item in scans:
            if isinstance(item, SkippedScan):
                continue
            labels, _ = self.mapper.query(item.points_world(), with_probs=False)
            write_predictions(self.out_dir, self.sequence_name, item.index, labels)
            if item.gt_labels is not None:
                score_scan(final, item, labels)
        return final
