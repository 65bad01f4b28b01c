"""Where a SemanticKITTI sequence's files are: the sequence folder a path names, and its scans.

Apart from the reader (`tisem.io.semantickitti`), which checks and loads what is in those
files, because a run's outputs (`tisem.io.kitti_predictions`) follow the same naming of
sequences without reading any input.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from tisem.errors import DatasetError

_BIN_RE = re.compile(r"^(\d+)\.bin$")


def normalise_sequence(sequence: str | int) -> str:
    """A sequence's folder name: 8 and "8" are "08"; a name that is not a number stays."""
    s = str(sequence).strip()
    return s.zfill(2) if s.isdigit() else s


def _list_sequences(root: Path) -> list[str]:
    seq_root = root / "sequences"
    if not seq_root.is_dir():
        return []
    return sorted(p.name for p in seq_root.iterdir() if (p / "velodyne").is_dir())


def find_sequence(path: str | os.PathLike, sequence: str | int | None) -> tuple[Path, str]:
    """The sequence folder and name `path` and `sequence` give (`SemanticKittiSequence`'s
    parameters); `DatasetError` saying what is there instead."""
    root = Path(path)
    if not root.exists():
        raise DatasetError(f"{root}: folder does not exist")
    if not root.is_dir():
        raise DatasetError(
            f"{root}: not a folder (expected a SemanticKITTI sequence folder "
            f"with velodyne/, or a dataset root with sequences/NN/)"
        )
    if (root / "velodyne").is_dir():
        if sequence is not None:
            return root, normalise_sequence(sequence)
        name = root.resolve().name
        return root, name if re.fullmatch(r"\d\d", name) else "00"
    if (root / "sequences").is_dir():
        found = _list_sequences(root)
        if sequence is None:
            raise DatasetError(
                f"{root}: is a dataset root; choose a sequence "
                f"(sequence= / --sequence), found: {', '.join(found) or 'none'}"
            )
        name = normalise_sequence(sequence)
        seq_dir = root / "sequences" / name
        if not (seq_dir / "velodyne").is_dir():
            raise DatasetError(
                f"{seq_dir}: no such sequence with a velodyne/ folder; "
                f"sequences found: {', '.join(found) or 'none'}"
            )
        return seq_dir, name
    raise DatasetError(
        f"{root}: no velodyne/ folder (not a SemanticKITTI sequence) and "
        f"no sequences/ folder (not a dataset root)"
    )


def scan_files(velodyne_dir: Path) -> dict[int, str]:
    """{scan id: file name} of the `NNNNNN.bin` scans; `DatasetError` when there are none or
    two files are the same scan (`8.bin` and `000008.bin`)."""
    bin_names: dict[int, str] = {}
    for p in sorted(velodyne_dir.iterdir()):
        m = _BIN_RE.match(p.name)
        if not m:
            continue
        sid = int(m.group(1))
        if sid in bin_names:
            raise DatasetError(
                f"{velodyne_dir}: {bin_names[sid]} and {p.name} are both "
                f"scan {sid}; each scan number must have one file"
            )
        bin_names[sid] = p.name
    if not bin_names:
        raise DatasetError(f"{velodyne_dir}: no NNNNNN.bin scans")
    return bin_names


def predictions_folder(path: Path, sequence: str) -> Path:
    """The folder of a sequence's prediction files that `path` names: `path` itself, or, for
    the root a semantic-kitti-api style run writes, `path/sequences/NN/predictions`; a
    `DatasetError` when there is no such folder."""
    nested = path / "sequences" / sequence / "predictions"
    if nested.is_dir():
        return nested
    if (path / "sequences").is_dir():
        found = _list_predictions(path)
        raise DatasetError(
            f"{nested}: no predictions of sequence {sequence} under this prediction root; "
            f"it has {', '.join(found) or 'none'}"
        )
    if not path.is_dir():
        raise DatasetError(f"{path}: predictions folder does not exist")
    return path


def _list_predictions(root: Path) -> list[str]:
    return sorted(p.name for p in (root / "sequences").iterdir() if (p / "predictions").is_dir())
