"""A stream of scans through the mapper in one call: progress, evaluation, results folder.

    result = run_pipeline(SemanticKittiSequence(path), load_config(), "results/run")
    print(results_table(result.metrics))

Writes `config.yaml`, `run.json`, `metrics.json`, per-point predictions in SemanticKITTI layout
(`sequences/NN/predictions/NNNNNN.label`, final-map protocol) and the map files. Bad scans
arrive as `SkippedScan`s: they are reported, the rest is mapped. The run itself, step by step
and resumable, is `tisem.run.MappingRun`.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import Any

from tisem.checkpoint import Checkpoint
from tisem.config import RunConfig
from tisem.errors import SkippedScan
from tisem.report import results_table
from tisem.run import MappingRun, OnScan, RunResult
from tisem.scan import Scan

__all__ = ["run_pipeline", "results_table", "RunResult"]


def run_pipeline(
    scans: Iterable[Scan | SkippedScan],
    cfg: RunConfig,
    out_dir: str | os.PathLike,
    *,
    progress: bool = True,
    on_scan: OnScan | None = None,
    write_outputs: bool = True,
    resume: Checkpoint | str | os.PathLike | None = None,
    **options: Any,
) -> RunResult:
    """Map every scan, then score and write everything (see module docstring).

    `options` are `MappingRun`'s: `sequence_name`, `total`, `source_info`, `checkpoint_every`,
    `checkpoint_dir`, `mapper`. `progress`: show a progress bar; `on_scan(mapper, scan, k)`
    is called after each integrated scan; `write_outputs=False` leaves out the map files.
    `resume` (a results folder, its checkpoint folder or file, or a `Checkpoint`) continues
    that run (`MappingRun.resume`): scans it holds are passed over, the metrics go on.
    """
    if resume is None:
        run = MappingRun(scans, cfg, out_dir, **options)
    elif "mapper" in options:
        raise ValueError("give either mapper= or resume=, not both")
    else:
        run = MappingRun.resume(scans, resume, cfg, out_dir, **options)
    return run.run(show_progress=progress, on_scan=on_scan, write_map_files=write_outputs)
