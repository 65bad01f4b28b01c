"""The logs a fleet or a batch maps: SemanticKITTI sequences, MCAP files, ROS 2 bags.

    logs = discover_logs(["/data/kitti/dataset", "robot7.mcap", "bags/robot8/"])
    scans = open_log(logs[0], first=100, last=199)     # Scan | SkippedScan, in order
    logs = discover_logs(["bags/"], recording={"gt_field": "gt_label"})  # how to read them

A dataset root (a folder with `sequences/NN/`) gives one log per sequence, a sequence folder
(with `velodyne/`) one; a recording one: an `.mcap`, `.db3` or ROS 1 `.bag` file, or a rosbag2
folder (one with `metadata.yaml`: its split files are one recording, read in order, and only
the first holds `/tf_static`). Recordings are read by `tisem.io.bag_open`, each with the
recording options it was discovered with (`McapOptions` fields: topic, label and ground-truth
fields, map frame, static transforms ...), which travel with the log to the process that maps
it. Scan ranges are positions in the log, inclusive.

World frames. Maps merge only in one world frame, so every log names its frame: a SemanticKITTI
sequence's poses are in its own first camera frame (`kitti:<sequence folder>`), unless the
folder has a `world_frame.txt` naming a frame it shares with others (the multi-robot synthetic
world writes one); an MCAP recording's poses are in its map frame, which is only known to be
shared within the recording (`mcap:<file>#<map frame>`), unless the fleet is told the logs
share it (`world_frame=`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from tisem.errors import DatasetError

__all__ = [
    "LogSpec",
    "discover_logs",
    "open_log",
    "read_losses",
    "recording_fields",
    "first_pose",
    "log_length",
    "kitti_world_frame",
    "WORLD_FRAME_FILE",
]

WORLD_FRAME_FILE = "world_frame.txt"


@dataclass(frozen=True)
class LogSpec:
    """One log: its kind ("kitti", or "mcap" for a recording in any of the formats bag_open
    reads), its file or folder, a short name, its frame, and for a recording how to read it
    (`McapOptions` fields but the scan range, plain JSON)."""

    kind: str
    path: str
    name: str
    world_frame: str
    options: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Plain JSON; a SemanticKITTI log (no options) as before options existed, so that
        the batch cells and fleet tasks it finished are still recognised as its."""
        out = dict(vars(self))
        if not out["options"]:
            del out["options"]
        return out


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


def _recording(path: Path, options: dict) -> LogSpec:
    """A recording as a log, once bag_open knows what it is (DatasetError in one line if not:
    a file that is no recording, a folder without one)."""
    from tisem.io.bag_open import identify

    identify(path)
    frame = options.get("map_frame", "map")
    name = path.stem if path.is_file() else path.name
    return LogSpec("mcap", str(path), name, f"mcap:{path.resolve()}#{frame}", dict(options))


def _recordings_inside(folder: Path) -> str:
    """For a refusal of a folder that is no log: the recordings it holds, and the two ways to
    give them (several logs, or one bag whose metadata is missing); "" when it holds none."""
    inside = sorted(p.name for p in folder.iterdir() if p.suffix in (".mcap", ".db3", ".bag"))
    if not inside:
        return ""
    listed = ", ".join(inside[:4]) + (", ..." if len(inside) > 4 else "")
    return (
        f"; it holds {listed}: give each as a log ({folder}/*{Path(inside[0]).suffix}), or, "
        f"if they are the split files of one bag, write its metadata with "
        f"`ros2 bag reindex {folder}`"
    )


def recording_fields(options) -> dict:
    """The recording options (an `McapOptions` or a dict of its fields) as a log keeps them:
    plain JSON, without the scan range and class count, which the run's config sets."""
    from tisem.io.mcap_options import McapOptions

    given = options if isinstance(options, dict) else vars(options)
    set_by_run = {"first", "last", "num_classes"}  # accepted, and left out
    known = {f.name for f in fields(McapOptions)} - set_by_run
    unknown = sorted(set(given) - known - set_by_run)
    if unknown:
        raise ValueError(f"recording options: unknown {unknown}; known: {sorted(known)}")
    kept = {k: v for k, v in given.items() if k in known}
    if "static_tf" in kept:  # tuples of tuples -> lists, as JSON gives them back
        kept["static_tf"] = [list(t) for t in kept["static_tf"]]
    McapOptions(**kept).validate()
    return kept


def discover_logs(
    paths: Iterable[str | os.PathLike],
    sequences: Iterable[str] | None = None,
    recording=None,
) -> list[LogSpec]:
    """Every log under `paths` (module docstring); `sequences` picks sequences of a dataset
    root, `recording` (an `McapOptions` or a dict of its fields) says how the recordings are
    read. Raises DatasetError naming a path that holds no log, ValueError for an option."""
    wanted = None if sequences is None else {str(s).zfill(2) for s in sequences}
    options = recording_fields(recording or {})
    logs: list[LogSpec] = []
    for given in paths:
        path = Path(given)
        if not path.exists():
            raise DatasetError(f"{path}: no such file or folder")
        if path.is_file():
            logs.append(_recording(path, options))
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
            logs.append(_recording(path, options))
        else:
            raise DatasetError(
                f"{path}: not a log (expected a SemanticKITTI sequence or dataset root, an "
                f".mcap, .db3 or ROS 1 .bag file, or a rosbag2 folder with its metadata.yaml)"
                + _recordings_inside(path)
            )
    names = [log.name for log in logs]
    if len(set(names)) != len(names):
        # logs named alike (two dataset roots with sequence 00): tell them apart by position
        logs = [dataclasses.replace(log, name=f"{k:03d}-{log.name}") for k, log in enumerate(logs)]
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
    num_classes: int | None = None,
):
    """The scans of positions first..last (inclusive) of the log, as its reader gives them
    (`len()` and iteration of `Scan | SkippedScan`; a recording's reader also says what it
    could not read, `.report`). `num_classes`: the map's, which bounds a recording's label
    values (default the SemanticKITTI 20)."""
    if log.kind == "kitti":
        from tisem.io.semantickitti import SemanticKittiSequence

        seq = SemanticKittiSequence(log.path, input=input)
        ids = seq.scan_ids
        if first >= len(ids):
            raise DatasetError(f"{log.path}: scan position {first} is past its {len(ids)} scans")
        stop = len(ids) - 1 if last is None else min(last, len(ids) - 1)
        return SemanticKittiSequence(log.path, input=input, first=ids[first], last=ids[stop])
    if log.kind == "mcap":
        from tisem.io.bag_open import open_scan_reader
        from tisem.io.mcap_options import McapOptions

        classes = {} if num_classes is None else {"num_classes": num_classes}
        options = McapOptions(**{**log.options, "first": first, "last": last, **classes})
        return open_scan_reader(log.path, options)
    raise ValueError(f"unknown log kind {log.kind!r}")


def read_losses(scans) -> list[str]:
    """What the reader of an opened log (`open_log`, after its scans were read) could not use
    besides the scans it skipped, one line each: a recording's lost messages, suspect scans,
    unknown labels (its report); none for a SemanticKITTI sequence, whose skipped scans say
    it all."""
    report = getattr(scans, "report", None)
    if report is None:
        return []
    return dataclasses.replace(report, skipped=[]).lines()
