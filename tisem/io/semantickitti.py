"""Reader for SemanticKITTI sequence folders.

Layout of one sequence folder::

    velodyne/NNNNNN.bin      float32 x y z remission
    labels/NNNNNN.label      uint32 ground truth: raw semantic id (lower 16 bits) + instance
    predictions/NNNNNN.label uint32 network labels, same encoding
    poses.txt                one 3x4 row-major pose per scan, in the LEFT CAMERA frame
    calib.txt                with a `Tr:` line (velodyne -> camera, 3x4 row-major)
    times.txt                optional, seconds per scan (absent -> 0.1 s spacing)

Label files of int64 (told by their size: a network's argmax saved as it is) or holding
train ids (`tisem.labels.to_train_ids`) are read too, with one warning per label folder.

The LiDAR pose of scan i is ``T_world_lidar = Tr^-1 . pose_i . Tr``, pose_i the i-th line of
poses.txt (the same for times.txt); a folder cut out of a sequence whose files hold one entry
per scan, all its scans numbered past their end, pairs them in order instead (logged). In the
KITTI odometry layout the poses are `dataset/poses/NN.txt` beside `dataset/sequences/NN/`
(same format), used when the sequence folder has no poses.txt. `poses=FILE` instead reads a
trajectory that is already in the LiDAR frame (KITTI or TUM format,
`kitti_files.read_trajectory`); calib.txt is then optional, and TUM's stamps are the scan times
where there is no times.txt.

Errors: a problem with the sequence as a whole (no `velodyne/`, two scan files with the same
number, no `Tr:` or two of them, a `Tr` that is not a rigid transform, no or empty
`poses.txt`, missing input label folder, empty frame range) raises `DatasetError` from the
constructor; a problem with one scan (truncated `.bin`, missing label file, label count !=
point count, 0 points, all points non-finite, no pose or time for it, a pose line that is not
a pose by `tisem.poses.pose_problem`, a time that is not plausible) raises `ScanError` from
``seq[k]`` and becomes a `SkippedScan` when iterating. Every message names the file, and for
poses.txt, times.txt and calib.txt the line.

A plausible time is a finite number of seconds in [0, MAX_TIME_S], and the map's clock never
runs backwards: of the selected scans, those whose times keep the longest non-decreasing run
are kept, each scan whose time breaks it (one wild value, or a time earlier than the scans
around it) is refused. So one bad time costs its own scan, never the ones after it. The
file helpers (calib.txt, poses.txt, times.txt) are tisem/io/kitti_files.py, finding the
sequence folder and its scans tisem/io/kitti_layout.py, and writing a run's per-scan outputs
(`write_predictions`, `write_dynamic_flags`) tisem/io/kitti_predictions.py.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from tisem.errors import DatasetError, ScanError, SkippedScan
from tisem.io.kitti_files import (
    MAX_TIME_S,
    camera_poses_to_lidar,
    entry_of_scan,
    out_of_order,
    read_calib_tr,
    read_pose_lines,
    read_poses,
    read_time_lines,
    read_times,
    read_trajectory,
)
from tisem.io.kitti_layout import find_sequence, predictions_folder, scan_files
from tisem.io.kitti_predictions import (
    prediction_file,
    read_dynamic_flags,
    write_dynamic_flags,
    write_predictions,
)
from tisem.labels import (
    LABEL_SPACES,
    SPACE_SEARCH_LIMIT,
    TrainIdNotes,
    deciding_space,
    label_space_of,
    moving_raw,
    read_alike,
    to_train_ids,
    train_to_raw,
)
from tisem.scan import KittiSource, Scan, finite_rows

__all__ = [
    "SemanticKittiSequence",
    "write_predictions",
    "write_dynamic_flags",
    "read_dynamic_flags",
    "prediction_file",
    "read_calib_tr",
    "read_poses",
    "read_pose_lines",
    "read_times",
    "camera_poses_to_lidar",
    "DEFAULT_SCAN_PERIOD_S",
    "MAX_TIME_S",
]

log = logging.getLogger(__name__)

# A network's argmax saved as it is (numpy's int64) is twice uint32's size: told by the size,
# with every value within uint32's range. Two uint32 files end to end give values past it.
# Files of half or a quarter the size are left to the count error: a uint32 file cut short is
# as likely as labels of 16 or 8 bits, and read so it would give every scan garbage labels.
INT64_BYTES = 8

DEFAULT_SCAN_PERIOD_S = 0.1  # 10 Hz, used when there is no times.txt
INPUTS = ("predictions", "labels")


class SemanticKittiSequence:
    """One SemanticKITTI sequence as a list of `Scan`s.

    Parameters
    ----------
    path: a sequence folder (with `velodyne/`) or a dataset root with `sequences/NN/`
        (then `sequence` is required).
    sequence: the sequence name ("08" or 8) under a dataset root; for a bare sequence folder it
        only sets `sequence_name` (default: the folder name when it is two digits, else "00").
    input: "predictions" (the network's labels feed the map) or "labels" (ground truth as input).
    first, last: inclusive range of scan ids (the numbers of the `velodyne/*.bin` files).
    poses: a trajectory file of LiDAR poses, one per scan (instead of poses.txt and `Tr`).
    predictions: the network's label files, when not the sequence's `predictions/`: a folder of
        `NNNNNN.label` files, or the root a semantic-kitti-api style run writes
        (`ROOT/sequences/NN/predictions/`).
    label_space: the label files hold raw SemanticKITTI ids ("raw", with instance bits), train
        ids ("train"), or either ("auto", per file: `tisem.labels.to_train_ids`; a warning
        names the first file read as train ids, `train_ids.sources` counts them).

    Attributes
    ----------
    sequence_dir, sequence_name, scan_ids (sorted ints in range), Tr (4x4 velodyne -> camera),
    poses_lidar ((len, 4, 4) float64 T_world_lidar aligned with `scan_ids`; NaN where
    poses.txt has no pose for that scan, see `has_pose`), times ((len,) float64 seconds aligned
    with `scan_ids`; NaN where times.txt is too short), has_ground_truth (a `labels/` folder),
    input_dir (the folder the input labels come from), num_poses (poses in poses.txt),
    entry_notes (a line each for poses.txt and times.txt when their entries are paired with
    the scans in order, as for a sequence's extract: `kitti_files.entry_of_scan`, and one for
    a `last` past the folder's last scan; logged),
    time_entries (the entry of times.txt, or of a TUM trajectory, of each scan; None without).

    ``seq[k]`` is the k-th scan of the selected range (not the scan id) and raises `ScanError`
    for a bad scan; iteration yields `Scan` or `SkippedScan` and never stops on a bad scan.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        sequence: str | int | None = None,
        input: str = "predictions",
        first: int = 0,
        last: int | None = None,
        poses: str | os.PathLike | None = None,
        label_space: str = "auto",
        predictions: str | os.PathLike | None = None,
    ):
        if input not in INPUTS:
            raise ValueError(f"input must be one of {INPUTS}, got {input!r}")
        if label_space not in LABEL_SPACES:
            raise ValueError(f"label_space must be one of {LABEL_SPACES}, got {label_space!r}")
        self.input, self.label_space = input, label_space
        self.train_ids = TrainIdNotes(log)
        self.label_widths: dict[str, str] = {}  # label source -> the line said: files of int64
        self.sequence_dir, self.sequence_name = find_sequence(path, sequence)

        d = self.sequence_dir
        self.velodyne_dir = d / "velodyne"
        self.labels_dir = d / "labels"
        self.predictions_dir = (
            d / "predictions"
            if predictions is None
            else predictions_folder(Path(predictions), self.sequence_name)
        )
        self.has_ground_truth = self.labels_dir.is_dir()
        self.input_dir = self.predictions_dir if input == "predictions" else self.labels_dir
        if not self.input_dir.is_dir():
            hint = ""
            if input == "predictions" and predictions is None:
                hint = (
                    "; the network's label files kept elsewhere: --predictions DIR (map-kitti, "
                    "kitti-to-mcap; predictions= in Python)"
                )
                if self.has_ground_truth:
                    hint += ", or map the ground truth with --input labels (input='labels')"
            raise DatasetError(
                f"{self.input_dir}: input label folder missing (input={input!r}); "
                f"folders present: "
                f"{', '.join(sorted(p.name for p in d.iterdir() if p.is_dir()))}"
                f"{hint}"
            )

        bin_names = scan_files(self.velodyne_dir)
        all_ids = sorted(bin_names)
        self.scan_ids = [i for i in all_ids if i >= first and (last is None or i <= last)]
        if not self.scan_ids:
            raise DatasetError(
                f"{self.velodyne_dir}: empty frame range first={first} last={last}; "
                f"scans present: {all_ids[0]}..{all_ids[-1]} ({len(all_ids)} files)"
            )
        self._bin_names = bin_names  # every scan of the folder, in range or not
        self._either: dict[str, str] = {}  # label source -> the space of its files that fit both

        lidar_all, pose_problems, stamps = self._read_poses(poses)
        self.num_poses = int(lidar_all.shape[0])
        ids = np.asarray(self.scan_ids, dtype=np.int64)
        # the pose of each scan: poses.txt's entry of its number, or of its place in an extract
        pose_of, note = entry_of_scan(all_ids, self.scan_ids, self.num_poses, self.poses_file)
        self.entry_notes = [note] if note else []
        if last is not None and last > all_ids[-1]:  # (a range written for a longer sequence)
            self.entry_notes.append(
                f"{self.velodyne_dir}: last={last} is past the folder's last scan "
                f"({all_ids[-1]}): scans {self.scan_ids[0]}..{self.scan_ids[-1]} are mapped"
            )
        self.has_pose = pose_of < self.num_poses
        self.poses_lidar = np.full((len(ids), 4, 4), np.nan)
        self.poses_lidar[self.has_pose] = lidar_all[pose_of[self.has_pose]]
        # why a scan cannot be used although its files can: {scan id: the ScanError message}
        self.problems: dict[int, str] = {
            sid: pose_problems[int(e)]
            for sid, e in zip(self.scan_ids, pose_of)
            if int(e) in pose_problems
        }

        self.times_file = d / "times.txt"
        if self.times_file.is_file():
            all_times, time_problems = read_time_lines(self.times_file)
            time_of, note = entry_of_scan(all_ids, self.scan_ids, all_times.size, self.times_file)
            self.entry_notes += [note] if note else []
            self.times = np.full(len(ids), np.nan)
            ok = time_of < all_times.size
            self.times[ok] = all_times[time_of[ok]]
            self._num_times = int(all_times.size)
            for sid, e in zip(self.scan_ids, time_of):
                if int(e) in time_problems:
                    self.problems.setdefault(sid, time_problems[int(e)])
            self.time_entries = time_of
            found = out_of_order(self.times, self.scan_ids, self.times_file, time_of)
            for k, why in found.items():
                self.problems.setdefault(self.scan_ids[k], why)
        elif stamps is not None:  # a TUM trajectory's stamps
            self.times_file = self.poses_file
            self.times = np.full(len(ids), np.nan)
            self.times[self.has_pose] = stamps[pose_of[self.has_pose]]
            self._num_times = int(stamps.size)
            self.time_entries = pose_of
            found = out_of_order(self.times, self.scan_ids, self.poses_file, pose_of)
            for k, why in found.items():
                self.problems.setdefault(self.scan_ids[k], why)
        else:
            self.times = ids.astype(np.float64) * DEFAULT_SCAN_PERIOD_S
            self._num_times = None
            self.time_entries = None
        for note in self.entry_notes:
            log.warning(note)

    def _read_poses(
        self, trajectory: str | os.PathLike | None
    ) -> tuple[np.ndarray, dict[int, str], np.ndarray | None]:
        """Every pose of the sequence in the LiDAR frame (M, 4, 4), {pose index: why a line is
        not a pose}, and the trajectory's stamps (TUM) or None; sets `Tr` and `poses_file`."""
        d = self.sequence_dir
        if trajectory is not None:
            self.poses_file = Path(trajectory)
            # the trajectory is the LiDAR's already; Tr only places the camera (MCAP /tf)
            self.Tr = read_calib_tr(d / "calib.txt") if (d / "calib.txt").is_file() else np.eye(4)
            poses, stamps, problems = read_trajectory(self.poses_file)
            return poses, problems, stamps
        self.Tr = read_calib_tr(d / "calib.txt")
        self.poses_file = d / "poses.txt"
        odometry = d.parent.parent / "poses" / f"{d.name}.txt"  # dataset/poses/NN.txt
        if not self.poses_file.is_file() and d.parent.name == "sequences" and odometry.is_file():
            self.poses_file = odometry
        if not self.poses_file.is_file():
            raise DatasetError(
                f"{self.poses_file}: poses file not found (nor {odometry}, the "
                f"KITTI odometry layout); give a LiDAR trajectory with --poses "
                f"FILE (KITTI or TUM format)"
            )
        poses_cam, problems = read_pose_lines(self.poses_file)
        return camera_poses_to_lidar(poses_cam, self.Tr), problems, None

    @property
    def reading_notes(self) -> list[str]:
        """How the files were read where they differ from SemanticKITTI's layout (the warning
        lines: extracts' entries paired in order, int64 label files, train ids), for the
        run's record."""
        return [*self.entry_notes, *self.label_widths.values(), *self.train_ids.lines]

    # ------------------------------------------------------------------ paths
    def scan_path(self, k: int) -> Path:
        sid = self.scan_ids[k]
        return self.velodyne_dir / self._bin_names[sid]

    def _label_path(self, folder: Path, sid: int) -> Path:
        stem = self._bin_names[sid][: -len(".bin")]
        return folder / f"{stem}.label"

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return len(self.scan_ids)

    def __repr__(self) -> str:
        return (
            f"SemanticKittiSequence({str(self.sequence_dir)!r}, "
            f"sequence={self.sequence_name!r}, input={self.input!r}, "
            f"scans {self.scan_ids[0]}..{self.scan_ids[-1]} ({len(self)}), "
            f"ground truth: {self.has_ground_truth})"
        )

    def __getitem__(self, k: int) -> Scan:
        if not isinstance(k, (int, np.integer)):
            raise TypeError(f"scan position must be an int, got {type(k).__name__}")
        n = len(self.scan_ids)
        if k < 0:
            k += n
        if not 0 <= k < n:
            raise IndexError(f"scan position {k} out of range for {n} scans")
        return self._load(int(k))

    def __iter__(self) -> Iterator[Scan | SkippedScan]:
        for k in range(len(self.scan_ids)):
            try:
                yield self._load(k)
            except ScanError as exc:
                yield SkippedScan(
                    index=self.scan_ids[k], name=str(self.scan_path(k)), reason=str(exc)
                )

    def label_values(self, k: int, what: str, n: int) -> np.ndarray:
        """The k-th scan's labels (a scan of n points) as raw ids, uint32: the file's values,
        or the raw ids of the train ids it holds. `what`: "predictions" or "labels";
        ScanError when there is no such file or it does not hold n labels."""
        sid = self.scan_ids[k]
        kind = "predictions" if what == "predictions" else "ground-truth"
        path = self._label_path(self._label_folder(what), sid)
        values = self._read_labels(path, sid, kind, n, self.scan_path(k).name)
        train, _, space = self._to_train_ids(values, what, path, noted=False)
        return values if space == "raw" else train_to_raw(train).astype(np.uint32)

    def _to_train_ids(self, values: np.ndarray, source: str, path: Path, noted: bool = True):
        """`to_train_ids` of a label file of `source` ("predictions" or "labels"), values that
        fit both spaces read in `_either_space`'s; `noted`: counted in `train_ids` (a file read
        a second time is not)."""
        space = self.label_space
        if space == "auto":
            space = label_space_of(values)
            if space == "either":
                space = "raw" if read_alike(values) else self._either_space(source)
        got = to_train_ids(values, space)
        if noted:
            self.train_ids.read(source, str(path), got[2])
        return got

    def _either_space(self, source: str) -> str:
        """The space a file of `source` whose values fit both is read in: that of the folder's
        first file of `source`, in scan order, whose values fit only one (raw where none of
        the first SPACE_SEARCH_LIMIT does). A folder holds one network's output, and a file
        then reads the same whatever was read before it: `seq[k]` in any order, any range of
        the folder."""
        if source not in self._either:
            self._either[source] = self._first_decided_space(source)
        return self._either[source]

    def _first_decided_space(self, source: str) -> str:
        for sid, bin_name in sorted(self._bin_names.items())[:SPACE_SEARCH_LIMIT]:
            path = self._label_path(self._label_folder(source), sid)
            try:
                n = (self.velodyne_dir / bin_name).stat().st_size // 16
                values = self._read_labels(path, sid, source, n, bin_name, noted=False)
            except (ScanError, OSError):  # a file a scan will skip for, or report, itself
                continue
            space = deciding_space(values)  # (an empty scan decides nothing: it is skipped)
            if space is not None:
                return space
        return "raw"

    def _label_folder(self, source: str) -> Path:
        """The folder of the label files of `source` ("predictions" or "labels")."""
        return self.predictions_dir if source == "predictions" else self.labels_dir

    def _read_labels(
        self, path: Path, sid: int, what: str, n: int, bin_name: str, noted: bool = True
    ) -> np.ndarray:
        """The n labels of a scan's label file, as uint32: SemanticKITTI's width, or int64 (a
        network's argmax saved as it is) where the size says so and the values fit (said once
        per `what` in `label_widths` where `noted`)."""
        if not path.is_file():
            raise ScanError(f"{path}: {what} label file missing for scan {sid}", sid, str(path))
        size = path.stat().st_size
        if size == INT64_BYTES * n and n:
            values = np.fromfile(path, dtype="<i8")
            if values.min() >= 0 and values.max() < 1 << 32:
                if noted and what not in self.label_widths:
                    self.label_widths[what] = (
                        f"{path}: this {what} file holds 64-bit integers, not SemanticKITTI's "
                        f"uint32 ({size} bytes for {n} points): read as such, here and in every "
                        f"other file so saved"
                    )
                    log.warning("%s", self.label_widths[what])
                return values.astype(np.uint32)
        if size % 4:
            raise ScanError(
                f"{path}: truncated label file ({size} bytes, not a multiple of 4)", sid, str(path)
            )
        if size != 4 * n:
            raise ScanError(
                f"{path}: label count differs from point count: {size // 4} labels for {n} "
                f"points in {bin_name}",
                sid,
                str(path),
            )
        return np.fromfile(path, dtype="<u4")

    def _load(self, k: int) -> Scan:
        sid = self.scan_ids[k]
        bin_path = self.scan_path(k)
        name = str(bin_path)
        try:
            size = bin_path.stat().st_size
            if size % 16:
                raise ScanError(
                    f"{bin_path}: truncated scan file ({size} bytes is not a multiple "
                    f"of 16 = 4 float32 x y z remission)",
                    sid,
                    name,
                )
            if size == 0:
                raise ScanError(f"{bin_path}: empty scan (0 points)", sid, name)
            if not self.has_pose[k]:
                raise ScanError(
                    f"{self.poses_file}: no pose for scan {sid} ({bin_path.name}); "
                    f"{self.poses_file.name} has {self.num_poses} poses (scans 0.."
                    f"{self.num_poses - 1})",
                    sid,
                    name,
                )
            if sid in self.problems:
                raise ScanError(self.problems[sid], sid, name)
            if not np.isfinite(self.times[k]):
                raise ScanError(
                    f"{self.times_file}: no time for scan {sid}; times.txt has "
                    f"{self._num_times} entries",
                    sid,
                    name,
                )
            data = np.fromfile(bin_path, dtype="<f4").reshape(-1, 4)
            n = data.shape[0]
            in_path = self._label_path(self.input_dir, sid)
            raw_in = self._read_labels(in_path, sid, self.input, n, bin_path.name)
            raw_gt = None
            if self.has_ground_truth:
                gt_path = self._label_path(self.labels_dir, sid)
                if self.input == "labels":
                    raw_gt = raw_in
                else:
                    raw_gt = self._read_labels(gt_path, sid, "ground-truth", n, bin_path.name)
            # non-finite points stay: the mapper drops them (tisem.scan.finite_rows, the one
            # rule) and the predictions file keeps one label per point of the .bin
            if not finite_rows(data[:, :3]).any():
                raise ScanError(f"{bin_path}: all {n} points are non-finite (NaN/inf)", sid, name)
            labels, unknown, space = self._to_train_ids(raw_in, self.input, in_path)
            gt = None
            unknown_gt = 0
            if raw_gt is not None:
                if self.input == "labels":
                    gt, unknown_gt = labels, unknown
                else:
                    gt, unknown_gt, _ = self._to_train_ids(raw_gt, "labels", gt_path)
            return Scan(
                points_sensor=data[:, :3],
                T_world_sensor=self.poses_lidar[k],
                stamp_s=float(self.times[k]),
                labels=labels,
                gt_labels=gt,
                index=sid,
                name=name,
                source=KittiSource(
                    unknown_raw_ids=unknown,
                    unknown_gt_ids=unknown_gt,
                    sequence=self.sequence_name,
                    input=self.input,
                ),
                # the moving ids (252-259) map to their static class's train id, and the
                # motion they say travels beside it
                moving=moving_raw(raw_in),
                gt_moving=None if raw_gt is None else moving_raw(raw_gt),
            )
        except ScanError:
            raise
        except (OSError, ValueError) as exc:
            raise ScanError(f"{bin_path}: cannot read scan {sid}: {exc}", sid, name) from exc
