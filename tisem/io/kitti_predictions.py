"""A run's per-scan outputs in the SemanticKITTI layout: `sequences/NN/predictions/NNNNNN.label`
(the mapped labels, as raw ids the standard tools score) and `NNNNNN.dynamic` beside it.

Apart from the sequence reader (`tisem.io.semantickitti`): these are written for every input,
MCAP recordings and synthetic drives too, and read back only by the commands that export them.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tisem.io.kitti_layout import normalise_sequence
from tisem.labels import train_to_raw


def prediction_file(
    out_root: str | os.PathLike, sequence_name: str | int, scan_id: int, suffix: str
) -> Path:
    """`out_root/sequences/NN/predictions/NNNNNN<suffix>`: where a run's per-scan outputs go."""
    folder = Path(out_root) / "sequences" / normalise_sequence(sequence_name) / "predictions"
    return folder / f"{int(scan_id):06d}{suffix}"


def _write_whole(path: Path, values: np.ndarray) -> Path:
    """`values` into `path`, its folders created, through a temporary name renamed at the end,
    so that a reader never sees a half-written file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    values.tofile(tmp)
    os.replace(tmp, path)
    return path


def write_predictions(
    out_root: str | os.PathLike, sequence_name: str | int, scan_id: int, train_labels: np.ndarray
) -> Path:
    """Write `out_root/sequences/NN/predictions/NNNNNN.label` (uint32 raw ids) and return its path.

    `train_labels` are train ids 0..19; they are stored as raw ids (`train_to_raw`) so that the
    standard SemanticKITTI tools can score them. Folders are created; the file is written to a
    temporary name first and renamed, so a reader never sees a half-written file.
    """
    raw = train_to_raw(np.asarray(train_labels).ravel()).astype("<u4", copy=False)
    return _write_whole(prediction_file(out_root, sequence_name, scan_id, ".label"), raw)


def write_dynamic_flags(
    out_root: str | os.PathLike, sequence_name: str | int, scan_id: int, dynamic: np.ndarray
) -> Path:
    """Write `out_root/sequences/NN/predictions/NNNNNN.dynamic`: one uint8 per point of the
    scan, 1 where free space found it dynamic (its own file beside the .label, so the
    SemanticKITTI layout stays valid); written like `write_predictions`."""
    flags = np.asarray(dynamic, dtype=bool).ravel().astype(np.uint8)
    return _write_whole(prediction_file(out_root, sequence_name, scan_id, ".dynamic"), flags)


def read_dynamic_flags(
    out_root: str | os.PathLike, sequence_name: str | int, scan_id: int, num_points: int
) -> np.ndarray | None:
    """The flags `write_dynamic_flags` wrote for a scan of `num_points` points, as bool; None
    where there is no such file (free space was off, or the scan was not mapped). A file of
    another length is not this scan's: ValueError naming it."""
    path = prediction_file(out_root, sequence_name, scan_id, ".dynamic")
    if not path.is_file():
        return None
    flags = np.fromfile(path, np.uint8)
    if len(flags) != num_points:
        raise ValueError(f"{path}: {len(flags)} flags for a scan of {num_points} points")
    return flags.astype(bool)
