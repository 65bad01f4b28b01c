"""The scans a results folder was mapped from, for pictures: a SemanticKITTI sequence or an
MCAP recording, behind one interface (`RunScans`).

`render` draws the network's labels, the map's and the ground truth of the same points, so it
reads the input again: the sequence folder that run.json names under `data`, or the recording
it names under `mcap`, read with the options the run used (`options`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from tisem.errors import DatasetError, ScanError
from tisem.scan import Scan

__all__ = ["RunScans", "open_run_scans"]


@dataclass
class RunScans:
    """A run's input scans: their ids, LiDAR poses (where known), where they come from, and
    `load(positions)`, which yields (position, Scan or why it cannot be read) in order."""

    sequence_name: str
    scan_ids: list[int]
    poses_lidar: np.ndarray  # (len, 4, 4)
    has_pose: np.ndarray  # (len,) bool
    has_ground_truth: bool
    origin: str  # the folder or the recording
    input_title: str  # what the first panel shows
    _load: Callable[[list[int]], Iterator[tuple[int, Scan | str]]] = field(repr=False)

    def load(self, positions: list[int]) -> Iterator[tuple[int, Scan | str]]:
        return self._load(sorted(positions))


def _resolve(path: str, results_dir: Path) -> Path:
    given = Path(path)
    if not given.is_absolute() and not given.exists() and (results_dir / given).exists():
        return results_dir / given  # a results folder moved together with its data
    return given


def _kitti_scans(data: Path, run: dict, config: dict) -> RunScans:
    from tisem.io.semantickitti import SemanticKittiSequence

    kwargs = dict(
        sequence=run.get("sequence"),
        first=int(run.get("first", config.get("first", 0))),
        last=run.get("last", config.get("last")),
        poses=run.get("poses"),
        predictions=run.get("predictions"),
        label_space=run.get("label_space", "auto"),
    )
    try:  # the network's labels as input when the folder has them
        seq, title = SemanticKittiSequence(data, input="predictions", **kwargs), "network labels"
    except DatasetError:
        fallback = config.get("input", "labels")
        if fallback == "predictions":
            raise
        seq, title = SemanticKittiSequence(data, input=fallback, **kwargs), f"input ({fallback})"

    def load(positions: list[int]) -> Iterator[tuple[int, Scan | str]]:
        for k in positions:
            try:
                yield k, seq[k]
            except ScanError as exc:
                yield k, f"{seq.scan_ids[k]}: {exc}"

    return RunScans(
        seq.sequence_name,
        list(seq.scan_ids),
        seq.poses_lidar,
        seq.has_pose,
        seq.has_ground_truth,
        str(seq.sequence_dir),
        title,
        load,
    )


def _recording_scans(path: Path, run: dict) -> RunScans:
    from tisem.extras import require

    require("mcap")
    from tisem.io.bag_open import open_scan_reader
    from tisem.io.mcap_reader import McapOptions

    options = McapOptions(**(run.get("options") or {}))
    reader = open_scan_reader(path, options)
    ids, poses = [], []
    for item in reader:  # one pass for the trajectory
        if isinstance(item, Scan):
            ids.append(item.index)
            poses.append(item.T_world_sensor)
    if not ids:
        raise DatasetError(f"{path}: no scan of the recording can be read")

    def load(positions: list[int]) -> Iterator[tuple[int, Scan | str]]:
        wanted = {ids[k]: k for k in positions}
        if not wanted:
            return
        # the reader stops at the last scan wanted, not at the end of the recording
        for item in open_scan_reader(path, replace(options, last=max(wanted))):
            if isinstance(item, Scan) and item.index in wanted:
                yield wanted[item.index], item

    return RunScans(
        str(run.get("sequence", "00")),
        ids,
        np.asarray(poses),
        np.ones(len(ids), dtype=bool),
        options.gt_field is not None,
        str(path),
        "network labels",
        load,
    )


def open_run_scans(run: dict, config: dict, results_dir: Path, run_path: Path) -> RunScans:
    """The input of the run whose run.json is `run` (at `run_path`)."""
    if "data" in run:
        return _kitti_scans(_resolve(run["data"], results_dir), run, config)
    if "mcap" in run:
        return _recording_scans(_resolve(run["mcap"], results_dir), run)
    raise ValueError(
        f"{run_path}: names no input ('data': a sequence folder, or 'mcap': a recording)"
    )
