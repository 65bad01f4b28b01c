"""A mapping run: a stream of scans through the mapper, then the final map scored and written.

    result = MappingRun(SemanticKittiSequence(path), load_config(), "results/run").run()
    result = MappingRun.resume(SemanticKittiSequence(path), "results/run").run()  # after a crash

The steps, in order: map every scan (scoring the network's labels and, with `online_eval`, the
map right after the scan), saving a checkpoint every N mapped scans; look every mapped scan up
in the finished map (the final-map protocol), writing its per-point predictions in
SemanticKITTI layout; write metrics.json; write the map files. config.yaml and run.json are
written with the first file, so a run that maps nothing leaves no folder (`tisem.run_writer`).

Bad scans arrive as `SkippedScan`s, or the pose gate (`tisem.pose_gate`: a pose far from the
drive) or the mapper refuses them: each is logged once, listed in metrics.json and has no
predictions file, and every protocol (input, online, final) scores the same scans, the mapped
ones. Ctrl-C is acted on between scans (`RunInterrupted`, after a checkpoint when checkpoints
are on); a disk that cannot take a checkpoint or the outputs ends the run with a `RunError`;
a store that cannot spill stops the mapping, and the scans mapped so far are scored and
written (`RunResult.stopped` says why).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import taichi as ti
from tqdm import tqdm

from tisem.checkpoint import CHECKPOINT_DIR, Checkpoint, open_checkpoint
from tisem.config import RunConfig
from tisem.errors import NothingMapped, RunError, RunInterrupted, SkippedScan, os_error_text
from tisem.evaluate import Confusion, network_labels, online_labels, score_scan
from tisem.interrupt import StopRequest
from tisem.io.mapfile import remove_stale_temp_files
from tisem.mapper import Mapper
from tisem.pose_gate import Anchor, PoseGate, Verdict
from tisem.progress import RunProgress
from tisem.report import run_metrics
from tisem.run_writer import RunWriter
from tisem.scan import Scan, finite_rows

log = logging.getLogger(__name__)

__all__ = ["MappingRun", "RunResult"]

OnScan = Callable[[Mapper, Scan, int], None]


@dataclass
class Relabelled:
    """How many points of the mapped scans the final map answers with another class than the
    network gave them: what a run without ground truth can say about what the map did."""

    points: int = 0  # finite points of the mapped scans
    changed: int = 0  # of them, answered with another class than the network's

    def add(self, scan: Scan, labels: np.ndarray) -> None:
        finite = finite_rows(scan.points_sensor)
        self.points += int(finite.sum())
        self.changed += int(((labels != network_labels(scan)) & finite).sum())

    def to_dict(self) -> dict:
        share = self.changed / self.points if self.points else None
        return {"points": self.points, "changed": self.changed, "share": share}


@dataclass
class RunResult:
    """A finished run: its metrics.json, the mapper holding the final map, where it wrote;
    `stopped`: why mapping ended before the stream did (None: it did not); `progress`: the
    run's accumulators (`is_mapped` asks it)."""

    metrics: dict
    mapper: Mapper
    out_dir: Path
    skipped: list[SkippedScan] = field(default_factory=list)
    trajectory: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    stopped: str | None = None
    progress: RunProgress | None = None

    def is_mapped(self, index: int) -> bool:
        """Whether the scan with this `Scan.index` was mapped (has predictions, is scored)."""
        return self.progress is not None and self.progress.is_mapped(index)


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

    def __init__(
        self,
        scans: Iterable[Scan | SkippedScan],
        cfg: RunConfig,
        out_dir: str | os.PathLike,
        *,
        sequence_name: str = "00",
        total: int | None = None,
        source_info: dict | None = None,
        checkpoint_every: int = 0,
        checkpoint_dir: str | os.PathLike | None = None,
        mapper: Mapper | None = None,
        progress: RunProgress | None = None,
    ):
        self.scans = scans
        self.cfg = cfg
        self.out_dir = Path(out_dir)
        self.sequence_name = sequence_name
        self.total = total
        self.checkpoint_every = int(checkpoint_every or 0)
        if self.checkpoint_every < 0:
            raise ValueError(f"checkpoint_every must be >= 0, got {checkpoint_every}")
        self.checkpoint_dir = (
            Path(checkpoint_dir) if checkpoint_dir is not None else self.out_dir / CHECKPOINT_DIR
        )
        # run.json; a resumed run finds its checkpoint cadence there
        self.info = dict(
            source_info or {}, checkpoint_every=self.checkpoint_every, sequence=sequence_name
        )
        self.files = RunWriter(self.out_dir, cfg, self.info, sequence_name, self.checkpoint_dir)
        self.mapper = mapper or Mapper(cfg.mapper)
        self.progress = progress or RunProgress.start(self.mapper.C)
        self.relabelled = Relabelled()  # counted by the final pass
        self._stop = StopRequest()

    # the writer keeps these two, set by the run: a write that fails names them
    @property
    def checkpointed_index(self) -> int | None:
        """`last_index` of the newest checkpoint (None: none yet)."""
        return self.files.checkpointed_index

    @property
    def stopped(self) -> str | None:
        """Why mapping ended before the stream did (None: it did not)."""
        return self.files.stopped

    @classmethod
    def resume(
        cls,
        scans: Iterable[Scan | SkippedScan],
        checkpoint: Checkpoint | str | os.PathLike,
        cfg: RunConfig | None = None,
        out_dir: str | os.PathLike | None = None,
        *,
        sequence_name: str | None = None,
        source_info: dict | None = None,
        checkpoint_every: int | None = None,
        **options,
    ) -> MappingRun:
        """The run a checkpoint (a `Checkpoint`, a results folder, its checkpoint folder or
        the file) belongs to, ready to go on: its map, its progress, and unless given, its
        config, results folder, sequence name, run.json and checkpoint cadence. `scans` is the
        whole stream again; what the checkpoint holds is passed over. A `cfg` whose mapper
        config differs from the checkpoint's is refused (ValueError) before any map is built.
        Temporary files a killed save left beside the checkpoint are removed.
        """
        ckpt = open_checkpoint(checkpoint)
        cfg = cfg if cfg is not None else ckpt.run_config()
        ckpt.check_run_config(cfg)
        remove_stale_temp_files(ckpt.path)
        source = ckpt.source
        mapper = ckpt.build_mapper(store_dir=cfg.mapper.store_dir)
        progress = ckpt.progress(mapper.C)
        log.info(
            "resuming from %s: %d scans mapped, up to scan %s",
            ckpt.path,
            progress.mapped,
            progress.last_index,
        )
        if source_info is None:
            source_info = {
                k: v for k, v in source.items() if k not in ("sequence", "checkpoint_every")
            }
        run = cls(
            scans,
            cfg,
            out_dir if out_dir is not None else ckpt.results_dir,
            sequence_name=sequence_name or source.get("sequence", "00"),
            source_info=source_info,
            checkpoint_every=(
                checkpoint_every
                if checkpoint_every is not None
                else source.get("checkpoint_every", 0)
            ),
            mapper=mapper,
            progress=progress,
            **options,
        )
        run.files.checkpointed_index = progress.last_index
        return run

    # ------------------------------------------------------------------ the steps
    def run(
        self,
        *,
        show_progress: bool = True,
        on_scan: OnScan | None = None,
        write_map_files: bool = True,
    ) -> RunResult:
        """Every step (module docstring); `on_scan(mapper, scan, k)` is called after each
        integrated scan (k: its position in the stream). Raises `NothingMapped` when every
        scan was skipped (nothing is written then), `RunInterrupted`, `RunError`."""
        with self._stop:
            final_scans = self.map_scans(show_progress, on_scan)
            if self.progress.mapped == 0:
                if self.stopped:
                    raise RunError(f"mapping stopped {self.stopped}; no scan was mapped")
                raise NothingMapped(self._nothing_mapped())
            final = self.final_pass(final_scans, show_progress)
        metrics = run_metrics(self.progress, final, self.mapper, self.cfg)
        metrics["relabelled"] = self.relabelled.to_dict()
        # how a reader read what it had to decide (tisem.io.semantickitti, mcap_reader)
        notes = getattr(self.scans, "reading_notes", None)
        if notes:
            metrics["input_read"] = list(notes)
        if self.stopped:
            metrics["stopped"] = self.stopped
        self.files.write_metrics(metrics)
        result = RunResult(
            metrics,
            self.mapper,
            self.out_dir,
            list(self.progress.skipped),
            self.progress.trajectory_array(),
            self.stopped,
            self.progress,
        )
        if write_map_files:
            self.files.write_map_files(self.mapper, result.trajectory, show_progress)
        return result

    def map_scans(
        self, show_progress: bool = True, on_scan: OnScan | None = None
    ) -> Iterable[Scan | SkippedScan]:
        """Integrate every scan not integrated before; returns the scans for the final pass
        (the stream itself when it can be read again, else the scans kept in memory)."""
        done_upto = self.progress.last_index
        keep_in_memory = iter(self.scans) is self.scans  # an iterator: read once
        kept: list[Scan] = []
        gate = PoseGate(self._anchor())
        bar = tqdm(
            self.scans,
            total=self.total,
            unit="scan",
            desc=f"mapping ({self.cfg.mapper.mode})",
            disable=not show_progress,
        )
        try:
            for k, item in enumerate(bar):
                if done_upto is not None and item.index <= done_upto:
                    # in the checkpoint already; the final pass still needs what was mapped
                    if (
                        keep_in_memory
                        and isinstance(item, Scan)
                        and self.progress.is_mapped(item.index)
                    ):
                        kept.append(item)
                    continue
                if not self._decide(
                    gate.offer(k, item), kept if keep_in_memory else None, on_scan, bar
                ):
                    break
                if self._stop.requested:
                    self._interrupted()
            else:
                self._decide(gate.finish(), kept if keep_in_memory else None, on_scan, bar)
        finally:
            bar.close()
        return kept if keep_in_memory else self.scans

    def _decide(
        self,
        verdicts: Iterable[Verdict],
        kept: list[Scan] | None,
        on_scan: OnScan | None,
        bar: tqdm,
    ) -> bool:
        """Map or skip what the pose gate let out, in order, checkpointing on cadence and
        stopping at the scan boundary after a Ctrl-C; False once mapping has to stop (the
        store could not spill)."""
        for k, item, reason in verdicts:
            if reason is not None:
                self._skip(SkippedScan(item.index, item.name, reason))
                continue
            if not self._integrate(item):
                if self.stopped:
                    return False
                continue
            if kept is not None:
                kept.append(item)
            if on_scan is not None:
                on_scan(self.mapper, item, k)
            if self.checkpoint_every and self.progress.mapped % self.checkpoint_every == 0:
                self.write_checkpoint()
            bar.set_postfix(voxels=f"{self.mapper.live_voxels / 1e3:.0f}k", refresh=False)
            if self._stop.requested:
                self._interrupted()
        return True

    def _anchor(self) -> Anchor | None:
        """Where the last mapped scan was (a resumed run's gate starts from there)."""
        if not self.progress.trajectory or self.progress.last_index is None:
            return None
        stamp = self.mapper.last_stamp_s
        return Anchor(
            self.progress.last_index,
            self.progress.trajectory_array()[-1],
            float("nan") if stamp is None else float(stamp),
        )

    def _integrate(self, scan: Scan) -> bool:
        """Map one scan and score it; False when the mapper refused it (it is skipped) or
        the store could not take what the window evicted (`stopped` says so)."""
        try:
            ti.sync()
            start = time.perf_counter()
            report = self.mapper.integrate(scan)
            ti.sync()
            seconds = time.perf_counter() - start
        except ValueError as exc:  # a scan the mapper refuses (bad labels, pose far away, ...)
            self._skip(SkippedScan(scan.index, scan.name, str(exc)))
            return False
        except OSError as exc:  # the store's spill folder is full or gone
            self.files.stopped = f"at scan {scan.index}: {os_error_text(exc)}"
            return False
        self.progress.add_mapped(scan, seconds, report)
        if report.dynamic is not None:  # free space: the scan's dynamic points
            self.files.write_dynamic_flags(scan.index, report.dynamic)
        if scan.gt_labels is not None:
            score_scan(self.progress.input, scan, network_labels(scan))
            if self.cfg.online_eval:
                labels, _ = self.mapper.query(scan.points_world(), with_probs=False)
                score_scan(self.progress.online, scan, online_labels(labels, scan, report.dynamic))
        return True

    def _skip(self, skipped: SkippedScan) -> None:
        """The one place a skipped scan is reported: one line as it happens (the end-of-run
        table counts them, metrics.json lists them)."""
        if self.progress.was_skipped(skipped.index):
            return
        self.progress.add_skipped(skipped)
        log.warning("%s", skipped.line())

    def _nothing_mapped(self) -> str:
        skipped = self.progress.skipped
        if not skipped:
            return "no scan could be mapped: the input holds no scans in the frame range"
        first = skipped[0]
        return (
            f"no scan could be mapped: all {len(skipped)} were skipped (the first, scan "
            f"{first.index}: {first.reason})"
        )

    def _interrupted(self) -> None:
        """Ctrl-C: checkpoint (when checkpoints are on) and stop."""
        checkpoint = None
        if self.checkpoint_every and self.progress.mapped:
            checkpoint = self.write_checkpoint()
        raise RunInterrupted(self.progress.last_index, checkpoint, self.out_dir)

    # ------------------------------------------------------------------ writing
    def write_checkpoint(self) -> Path:
        """The map and the progress so far, to `checkpoint_dir` (atomically); a disk that
        cannot take it raises RunError (the previous checkpoint is kept)."""
        return self.files.write_checkpoint(self.mapper, self.progress)

    def final_pass(
        self, scans: Iterable[Scan | SkippedScan], show_progress: bool = False
    ) -> Confusion:
        """The final-map protocol: every mapped scan looked up in the finished map; writes its
        predictions (one label per point of the scan) and returns the pooled confusion.
        Scans that were not mapped are passed over: no predictions file, not scored."""
        self.files.write_info()
        final = Confusion(self.mapper.C)
        self.relabelled = Relabelled()
        # minutes on a long drive: the bar counts the mapped scans it looks up
        for item in tqdm(
            scans,
            total=self.progress.mapped,
            unit="scan",
            disable=not show_progress,
            desc="final map: predictions",
        ):
            if not isinstance(item, Scan) or not self.progress.is_mapped(item.index):
                continue
            labels, _ = self.mapper.query(item.points_world(), with_probs=False)
            self.files.write_predictions(item.index, labels)
            self.relabelled.add(item, labels)
            if item.gt_labels is not None:
                score_scan(final, item, labels)
            if self._stop.requested:
                self._interrupted()
        return final
