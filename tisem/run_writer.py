"""What a mapping run writes into its results folder, and the one error a failed write is.

config.yaml and run.json go first, with the run's first checkpoint or predictions, so a run
that maps nothing leaves no folder behind; then each scan's dynamic flags, the checkpoints,
the predictions, metrics.json and the map files. Any of them that the disk cannot take (full,
gone, read-only) ends the run with one `RunError` line: what could not be written, where, and
which checkpoint is kept to resume from. Apart from `tisem.run` so that the run reads as its
steps, and every file of the folder fails the same way from one place.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tisem import outputs
from tisem.checkpoint import save_checkpoint
from tisem.config import RunConfig
from tisem.errors import RunError, os_error_text
from tisem.io.kitti_predictions import write_dynamic_flags, write_predictions

if TYPE_CHECKING:
    from tisem.mapper import Mapper
    from tisem.progress import RunProgress

__all__ = ["RunWriter"]


class RunWriter:
    """The files of one run in `out_dir` (module docstring): `info` is its run.json,
    `sequence_name` names the predictions folder, checkpoints go to `checkpoint_dir`.

    `checkpointed_index`: `last_index` of the newest checkpoint (None: none yet); `stopped`:
    why mapping ended before the stream did (None: it did not). A failed write names both.
    """

    def __init__(
        self,
        out_dir: Path,
        cfg: RunConfig,
        info: dict,
        sequence_name: str,
        checkpoint_dir: Path,
    ):
        self.out_dir = out_dir
        self.cfg = cfg
        self.info = info
        self.sequence_name = sequence_name
        self.checkpoint_dir = checkpoint_dir
        self.checkpointed_index: int | None = None
        self.stopped: str | None = None
        self._info_written = False

    @contextmanager
    def writing(self, what: str) -> Iterator[None]:
        """Inside: an OSError (a full disk, a folder that cannot be written) becomes one
        RunError line saying what could not be written and what is kept."""
        try:
            yield
        except OSError as exc:
            if self.checkpointed_index is not None:
                kept = (
                    f"the checkpoint of scan {self.checkpointed_index} is kept: continue with "
                    f"--resume {self.out_dir} once there is room"
                )
            else:
                kept = "no checkpoint to resume from"
            stopped = f" (mapping had stopped {self.stopped})" if self.stopped else ""
            raise RunError(
                f"cannot write {what} in {self.out_dir}: {os_error_text(exc)}; {kept}{stopped}"
            ) from None

    def write_info(self) -> None:
        """config.yaml and run.json, with the first file the run writes."""
        if not self._info_written:
            with self.writing("config.yaml and run.json"):
                outputs.write_run_info(self.out_dir, self.cfg, self.info)
            self._info_written = True

    @contextmanager
    def _file(self, what: str) -> Iterator[None]:
        """Writing one of the run's files: config.yaml and run.json first, if not yet."""
        self.write_info()
        with self.writing(what):
            yield

    def write_checkpoint(self, mapper: Mapper, progress: RunProgress) -> Path:
        """The map and the progress so far, to `checkpoint_dir` (atomically); a disk that
        cannot take it raises RunError (the previous checkpoint is kept)."""
        with self._file("the checkpoint"):
            path = save_checkpoint(
                self.checkpoint_dir, mapper, progress, run_config=self.cfg, source=self.info
            )
        self.checkpointed_index = progress.last_index
        return path

    def write_dynamic_flags(self, index: int, dynamic: np.ndarray) -> None:
        """The scan's per-point dynamic flags, beside its predictions."""
        with self._file("the dynamic flags"):
            write_dynamic_flags(self.out_dir, self.sequence_name, index, dynamic)

    def write_predictions(self, index: int, labels: np.ndarray) -> None:
        """The scan's per-point labels in the final map."""
        with self._file("the predictions"):
            write_predictions(self.out_dir, self.sequence_name, index, labels)

    def write_metrics(self, metrics: dict) -> None:
        with self._file("metrics.json"):
            outputs.write_metrics(self.out_dir, metrics)

    def write_map_files(self, mapper: Mapper, trajectory: np.ndarray, progress: bool) -> None:
        """map.npz, map.ply, map_bev.png of the finished map (`progress`: a bar over them)."""
        with self._file("the map files"):
            outputs.write_map_files(
                self.out_dir, mapper, self.cfg.mapper, trajectory, progress=progress
            )
