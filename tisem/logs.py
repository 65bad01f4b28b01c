"""The logs a fleet or a batch maps: SemanticKITTI sequences, MCAP files, ROS 2 bags.

    logs = discover_logs(["/data/kitti/dataset", "robot7.mcap", "bags/robot8/"])
    scans = open_log(logs[0], first=100, last=199)     # Scan | SkippedScan, in order

A dataset root (a folder with `sequences/NN/`) gives one log per sequence, a sequence folder
(with `velodyne/`) one, an `.mcap` file one, and a ROS 2 bag (a folder with `metadata.yaml`) one
per `.mcap` file in it. Scan ranges are positions in the log, inclusive.

World frames. Maps merge only in one world frame, so every log names its frame: a SemanticKITTI
sequence's poses are in its own first camera frame (`kitti:<sequence folder>`), unless the
folder has a `world_frame.txt` naming a frame it shares with others (the multi-robot synthetic
world writes one); an MCAP recording's poses are in its map frame, which is only known to be
shared within the recording (`mcap:<file>#<map frame>`), unless the fleet is told the logs
share it (`world_frame=`).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tisem.errors import DatasetError

__all__ = [
    "LogSpec",
    "discover_logs",
    "open_log",
    "first_pose",
    "log_length",
    "kitti_world_frame",
    "WORLD_FRAME_FILE",
]

WORLD_FRAME_FILE = "world_frame.txt"


@dataclass(frozen=True)
class LogSpec:
    """One log: its kind ("kitti" or "mcap"), its file or folder, a short name, its frame."""

    kind: str
    path: str
    name: str
    world_frame: str

    def to_dict(self) -> dict:
        return dict(vars(self))


def kitti_world_frame(sequence_dir: str | os.PathLike) -> str:
    """The world frame of a SemanticKITTI sequence folder (module docstring)."""
    folder = Path(sequence_dir)
    named = folder / WORLD_FRAME_FILE
    if named.is_file():
        text = named.read_text().strip()
        if text:
            return text
    return f"kitti:{folder.resolve()}"


def _kitti(folder: Path, name: str | None = None) -> LogSpec:
    return LogSpec("kitti", str(folder), name or folder.name, kitti_world_frame(folder))


def _mcap(file: Path, map_frame: str, name: str | None = None) -> LogSpec:
    return LogSpec("mcap", str(file), name or file.stem, f"mcap:{file.resolve()}#{map_frame}")


def discover_logs(
    paths: Iterable[str | os.PathLike],
    sequences: Iterable[str] | None = None,
    map_frame: str = "map",
) -> list[LogSpec]:
    """Every log under `paths` (module docstring); `sequences` picks sequences of a dataset
    root. Raises DatasetError naming a path that holds no log."""
    wanted = None if sequences is None else {str(s).zfill(2) for s in sequences}
    logs: list[LogSpec] = []
    for given in paths:
        path = Path(given)
        if path.is_file() and path.suffix == ".mcap":
            logs.append(_mcap(path, map_frame))
        elif (path / "velodyne").is_dir():
            logs.append(_kitti(path))
        elif (path / "sequences").is_dir():
            found = sorted(p for p in (path / "sequences").iterdir() if (p / "velodyne").is_dir())
            found = [p for p in found if wanted is None or p.name in wanted]
            if not found:
                raise DatasetError(
                    f"{path}: no sequence folders" + (f" among {sorted(wanted)}" if wanted else "")
                )
            logs += [_kitti(p) for p in found]
        elif (path / "metadata.yaml").is_file():
            files = sorted(path.glob("*.mcap"))
            if not files:
                raise DatasetError(
                    f"{path}: a ROS 2 bag without .mcap files (only MCAP storage is read)"
                )
            logs += [_mcap(f, map_frame, f"{path.name}/{f.stem}") for f in files]
        else:
            raise DatasetError(
                f"{path}: not a log (expected a SemanticKITTI sequence or "
                f"dataset root, an .mcap file or a ROS 2 bag folder)"
            )
    names = [log.name for log in logs]
    if len(set(names)) != len(names):
        # logs named alike (two dataset roots with sequence 00): tell them apart by position
        logs = [
            LogSpec(log.kind, log.path, f"{k:03d}-{log.name}", log.world_frame)
            for k, log in enumerate(logs)
        ]
    return logs


def log_length(log: LogSpec, input: str = "predictions") -> int:
    """The number of scans in the log (an MCAP file is surveyed once for it)."""
    return len(open_log(log, input=input))


def first_pose(log: LogSpec, input: str = "predictions") -> tuple[np.ndarray, float] | None:
    """(T_world_sensor, stamp) of the log's first scan when it is cheap to know (a
    SemanticKITTI sequence: poses.txt and times.txt), else None (also for a log that cannot
    be read: its task will say why)."""
    if log.kind != "kitti":
        return None
    from tisem.io.semantickitti import SemanticKittiSequence

    try:
        seq = SemanticKittiSequence(log.path, input=input)
    except (DatasetError, OSError, ValueError):
        return None
    if not seq.has_pose[0] or not np.isfinite(seq.times[0]):
        return None
    return seq.poses_lidar[0], float(seq.times[0])


def open_log(
    log: LogSpec,
    first: int = 0,
    last: int | None = None,
    input: str = "predictions",
    mcap_options: dict | None = None,
):
    """The scans of positions first..last (inclusive) of the log, as its reader gives them
    (`len()` and iteration of `Scan | SkippedScan`)."""
    if log.kind == "kitti":
        from tisem.io.semantickitti import SemanticKittiSequence

        seq = SemanticKittiSequence(log.path, input=input)
        ids = seq.scan_ids
        if first >= len(ids):
            raise DatasetError(f"{log.path}: scan position {first} is past its {len(ids)} scans")
        stop = len(ids) - 1 if last is None else min(last, len(ids) - 1)
        return SemanticKittiSequence(log.path, input=input, first=ids[first], last=ids[stop])
    if log.kind == "mcap":
        from tisem.io.mcap_reader import McapOptions, McapScanReader

        options = McapOptions(**dict(mcap_options or {}, first=first, last=last))
        return McapScanReader(log.path, options)
    raise ValueError(f"unknown log kind {log.kind!r}")
