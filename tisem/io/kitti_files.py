"""The text files of a SemanticKITTI sequence: calib.txt (`Tr:`), poses.txt and times.txt.

Each line is checked on its own: a line that is not a pose, or not a plausible time, is
reported with its file and line number ({line index: message}), so the reader can refuse that
one scan and map the others; `read_calib_tr` refuses the sequence (there is one calibration).

A plausible time is a finite number of seconds in [0, MAX_TIME_S] (seconds since the start of
the drive, or since the Unix epoch); `out_of_order` finds the times that would run the map's
clock backwards. `entry_of_scan` says which entry of poses.txt or times.txt is a scan's.
"""

from __future__ import annotations

import logging
import os
from bisect import bisect_right
from pathlib import Path

import numpy as np

from tisem.errors import DatasetError
from tisem.poses import pose_problem

__all__ = [
    "read_calib_tr",
    "read_pose_lines",
    "read_poses",
    "read_time_lines",
    "read_times",
    "read_trajectory",
    "out_of_order",
    "entry_of_scan",
    "entry_texts",
    "camera_poses_to_lidar",
    "MAX_TIME_S",
]

log = logging.getLogger(__name__)

MAX_TIME_S = 1.0e10  # the year 2286 in Unix time: any later stamp is corrupt data


def _row_to_4x4(values: np.ndarray) -> np.ndarray:
    T = np.eye(4, dtype=np.float64)
    T[:3, :4] = np.asarray(values, dtype=np.float64).reshape(3, 4)
    return T


def _parse_pose_row(text: str, where: str, line: str, subject: str) -> np.ndarray:
    """Twelve numbers (a 3x4 row-major transform, as calib.txt and poses.txt store them) as a
    (4, 4) float64 matrix. The DatasetError for anything else starts with `where` (file:line)
    and names `line` (what the line is) or `subject` (what it holds)."""
    try:
        values = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise DatasetError(
            f"{where}: malformed {line}, non-numeric value in {text.strip()[:80]!r}"
        ) from None
    if values.size != 12:
        raise DatasetError(
            f"{where}: malformed {line}, expected 12 numbers (3x4 row-major), got {values.size}"
        )
    if not np.all(np.isfinite(values)):
        raise DatasetError(f"{where}: {subject} has NaN/inf values")
    return _row_to_4x4(values)


def _entry_lines(path: Path, what: str, quiet: bool = False) -> list[tuple[int, str]]:
    """The non-blank lines of a one-entry-per-line file as (line number, text). A blank line
    is an editor's stray newline, not an entry: skipping it keeps every later entry with its
    own scan (the lines still name their place in the file); it is logged once (`quiet`: a
    file read again is not)."""
    numbered = list(enumerate(_read_text(path, what).splitlines(), start=1))
    blank = [n for n, line in numbered if not line.strip()]
    last = max((n for n, line in numbered if line.strip()), default=0)
    inner = [n for n in blank if n < last]
    if inner and not quiet:
        log.warning(
            "%s: blank line%s %s ignored (one entry per line)",
            path,
            "s" if len(inner) > 1 else "",
            ", ".join(map(str, inner[:5])) + (", ..." if len(inner) > 5 else ""),
        )
    return [(n, line) for n, line in numbered if line.strip()]


def _read_text(path: Path, what: str) -> str:
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read {what}: {exc}") from exc


# the velodyne -> camera line: odometry and SemanticKITTI's key, the 3D object and tracking
# benchmarks' (the same 12 numbers)
TR_KEYS = ("Tr", "Tr_velo_to_cam", "Tr_velo_cam")


def read_calib_tr(path: str | os.PathLike) -> np.ndarray:
    """The `Tr:` line of a SemanticKITTI calib.txt as a (4, 4) float64 velodyne -> camera matrix
    (or `Tr_velo_to_cam:` / `Tr_velo_cam:`, as KITTI's object and tracking calibrations name it).

    Raises DatasetError (naming the file and line) when the file is missing, has no `Tr:`
    line or two of them, or the line is not 12 finite numbers forming a rigid transform
    (`tisem.poses.pose_problem`: a rotation, not scaled, sheared or mirrored).
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(
            f"{path}: calibration file not found (needs a 'Tr:' line, velodyne -> camera)"
        )
    found: tuple[int, np.ndarray] | None = None
    for lineno, line in enumerate(_read_text(path, "calibration file").splitlines(), start=1):
        key, sep, rest = line.partition(":")
        if not sep or key.strip() not in TR_KEYS:
            continue
        name = f"'{key.strip()}:'"
        if found is not None:
            raise DatasetError(
                f"{path}:{lineno}: a second {name} line (the first velodyne -> camera line is "
                f"line {found[0]}); the calibration must be one transform"
            )
        T = _parse_pose_row(rest, f"{path}:{lineno}", f"{name} line", f"{name} line")
        problem = pose_problem(T)
        if problem is not None:
            raise DatasetError(
                f"{path}:{lineno}: {name} (velodyne -> camera) is not a rigid transform: {problem}"
            )
        found = (lineno, T)
    if found is None:
        raise DatasetError(f"{path}: no 'Tr:' line (velodyne -> camera calibration) in the file")
    return found[1]


def read_pose_lines(path: str | os.PathLike) -> tuple[np.ndarray, dict[int, str]]:
    """poses.txt (one 3x4 row-major pose per line) as (M, 4, 4) float64, NaN where a line is
    not a pose, and {line index: why} for those lines (messages name the file and line).

    Blank lines are ignored (logged when inside the file). A line is a pose when it holds 12
    finite numbers that `tisem.poses.pose_problem` accepts. DatasetError when the file is
    missing, unreadable or empty. The poses are in the frame they are stored in (the left camera for
    SemanticKITTI): see `camera_poses_to_lidar`.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: poses file not found (one 3x4 pose per scan)")
    lines = _entry_lines(path, "poses file")
    if not lines:
        raise DatasetError(f"{path}: the poses file is empty (one 3x4 pose per scan)")
    poses = np.full((len(lines), 4, 4), np.nan)
    problems: dict[int, str] = {}
    for i, (lineno, line) in enumerate(lines):
        where = f"{path}:{lineno}"
        try:
            T = _parse_pose_row(line, where, f"pose line (pose {i})", f"pose {i}")
        except DatasetError as exc:
            problems[i] = str(exc)
            continue
        problem = pose_problem(T)
        if problem is not None:
            problems[i] = f"{where}: pose {i} is not a pose: {problem}"
            continue
        poses[i] = T
    return poses, problems


def read_trajectory(
    path: str | os.PathLike,
) -> tuple[np.ndarray, np.ndarray | None, dict[int, str]]:
    """A trajectory of LiDAR poses, one per scan in order: (M, 4, 4) float64 poses (NaN where
    a line is not a pose), the TUM stamps (M,) in seconds or None, and {pose index: why}.

    Two formats, told apart by the first line: KITTI (12 numbers, a 3x4 row-major pose, as
    poses.txt but already in the LiDAR frame, e.g. a KISS-ICP result) and TUM (8 numbers:
    `t x y z qx qy qz qw`; lines starting with `#` are comments). DatasetError when the file
    is missing, empty or in neither format.
    """
    from tisem.io.tf import quat_to_matrix

    path = Path(path)
    if not path.is_file():
        raise DatasetError(
            f"{path}: trajectory file not found (--poses: one LiDAR pose per "
            f"scan, KITTI or TUM format)"
        )
    rows = [
        (i + 1, line)
        for i, line in enumerate(_read_text(path, "trajectory").splitlines())
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not rows:
        raise DatasetError(f"{path}: the trajectory file is empty")
    width = len(rows[0][1].split())
    if width == 12:
        poses, problems = read_pose_lines(path)
        return poses, None, problems
    if width != 8:
        raise DatasetError(
            f"{path}:{rows[0][0]}: {width} numbers; a trajectory line is KITTI "
            f"(12: a 3x4 pose) or TUM (8: t x y z qx qy qz qw)"
        )
    poses = np.full((len(rows), 4, 4), np.nan)
    stamps = np.full(len(rows), np.nan)
    problems: dict[int, str] = {}
    for k, (lineno, line) in enumerate(rows):
        where = f"{path}:{lineno}"
        try:
            values = np.array([float(v) for v in line.split()], dtype=np.float64)
        except ValueError:
            problems[k] = f"{where}: non-numeric value in {line.strip()[:80]!r}"
            continue
        if values.size != 8 or not np.all(np.isfinite(values)) or not values[4:].any():
            problems[k] = (
                f"{where}: expected 8 finite numbers t x y z qx qy qz qw (a unit "
                f"quaternion), got {line.strip()[:80]!r}"
            )
            continue
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(values[4:])
        T[:3, 3] = values[1:4]
        problem = pose_problem(T)
        if problem is not None:
            problems[k] = f"{where}: pose {k} is not a pose: {problem}"
            continue
        poses[k], stamps[k] = T, values[0]
    return poses, stamps, problems


def read_poses(path: str | os.PathLike) -> np.ndarray:
    """poses.txt as (M, 4, 4) float64 (`read_pose_lines`); any line that is not a pose raises
    DatasetError naming the file and line."""
    poses, problems = read_pose_lines(path)
    if problems:
        raise DatasetError(problems[min(problems)])
    return poses


def camera_poses_to_lidar(poses: np.ndarray, Tr: np.ndarray) -> np.ndarray:
    """Camera-frame poses -> LiDAR poses: ``T_world_lidar = Tr^-1 . pose . Tr``.

    `poses` is (4, 4) or (M, 4, 4) (3x4 rows are accepted too); `Tr` is velodyne -> camera.
    The world frame stays the first camera frame, as in SemanticKITTI.
    """
    poses = np.asarray(poses, dtype=np.float64)
    Tr = np.asarray(Tr, dtype=np.float64)
    if Tr.shape == (3, 4):
        Tr = _row_to_4x4(Tr)
    if poses.shape[-2:] == (3, 4):
        full = np.zeros(poses.shape[:-2] + (4, 4))
        full[..., :3, :] = poses
        full[..., 3, 3] = 1.0
        poses = full
    if Tr.shape != (4, 4) or poses.shape[-2:] != (4, 4):
        raise ValueError(f"need Tr (4, 4) and poses (..., 4, 4), got {Tr.shape} and {poses.shape}")
    Tr_inv = np.linalg.inv(Tr)
    return Tr_inv @ poses @ Tr


def read_time_lines(path: str | os.PathLike) -> tuple[np.ndarray, dict[int, str]]:
    """times.txt (one time in seconds per line) as (M,) float64, NaN where a line is not a
    plausible time, and {line index: why} for those lines (messages name the file and line).
    Blank lines are ignored (`read_pose_lines`); DatasetError when the file cannot be read."""
    path = Path(path)
    lines = _entry_lines(path, "times file")
    times = np.full(len(lines), np.nan)
    problems: dict[int, str] = {}
    for i, (lineno, line) in enumerate(lines):
        where = f"{path}:{lineno}"
        fields = line.split()
        try:
            if len(fields) != 1:
                raise ValueError
            t = float(fields[0])
        except ValueError:
            problems[i] = (
                f"{where}: malformed time line, expected one number, got {line.strip()[:80]!r}"
            )
            continue
        if not (np.isfinite(t) and 0.0 <= t <= MAX_TIME_S):
            problems[i] = (
                f"{where}: time {t:g} s is not a plausible time (finite, 0 to {MAX_TIME_S:.0e} s)"
            )
            continue
        times[i] = t
    return times, problems


def read_times(path: str | os.PathLike) -> np.ndarray:
    """times.txt as (M,) float64 (`read_time_lines`); DatasetError naming the file and line
    for a line that is not a plausible time."""
    times, problems = read_time_lines(path)
    if problems:
        raise DatasetError(problems[min(problems)])
    return times


def entry_texts(path: str | os.PathLike) -> list[str]:
    """The entries of a one-entry-per-line file (times.txt) as text, blank lines skipped as
    the readers skip them: entry i is `read_time_lines`' i-th."""
    return [line for _, line in _entry_lines(Path(path), "times file", quiet=True)]


def out_of_order(
    times: np.ndarray, scan_ids: list[int], path: Path, entries: np.ndarray | None = None
) -> dict[int, str]:
    """{position: why} for the scans whose time would run the map's clock backwards.

    `times` (NaN: no time) belong to the scans `scan_ids`, in order, each the entry of `path`
    given by `entries` (default: its scan number). The longest run of non-decreasing times is
    kept (the first such run found), so one wild time costs its own scan only; every other
    scan with a time is out of order and named with its line.
    """
    entries = np.asarray(scan_ids) if entries is None else entries
    known = [k for k in range(len(times)) if np.isfinite(times[k])]
    # patience sorting: tails[j] = the smallest last time of a non-decreasing run of j + 1
    tails: list[float] = []
    tail_at: list[int] = []
    before: dict[int, int | None] = {}
    for k in known:
        j = bisect_right(tails, times[k])
        before[k] = tail_at[j - 1] if j else None
        if j == len(tails):
            tails.append(times[k])
            tail_at.append(k)
        else:
            tails[j], tail_at[j] = times[k], k
    kept: set[int] = set()
    k = tail_at[-1] if tail_at else None
    while k is not None:
        kept.add(k)
        k = before[k]
    ordered = sorted(kept)
    problems = {}
    for k in known:
        if k in kept:
            continue
        prev = max((j for j in ordered if j < k), default=None)
        nxt = min((j for j in ordered if j > k), default=None)
        around = " and ".join(
            f"scan {scan_ids[j]} at {times[j]:g} s" for j in (prev, nxt) if j is not None
        )
        problems[k] = (
            f"{path}:{entries[k] + 1}: time {times[k]:g} s is out of order "
            f"({around}): the map's clock cannot run backwards"
        )
    return problems


def entry_of_scan(
    folder_ids: list[int], scan_ids: list[int], entries: int, path: Path
) -> tuple[np.ndarray, str | None]:
    """The entry of `path` (a pose or time, by index) for each of `scan_ids`, and a note when
    they are not paired by number.

    SemanticKITTI numbers the entries by scan: entry i is scan i's. A folder cut out of a
    sequence (scans 1000-1004, say) often carries only its own entries, one per scan file
    (`folder_ids`, the whole folder, not the selected range), every scan numbered past the
    file's end: then the k-th entry is the folder's k-th scan's, and the note says so. Any
    other mismatch (a scan file missing, a file cut short) keeps the numbers: pairing those in
    order would shift every scan after the gap onto its neighbour's entry."""
    ids = np.asarray(scan_ids, dtype=np.int64)
    if entries != len(folder_ids) or folder_ids[0] < entries:
        return ids, None
    position = {sid: k for k, sid in enumerate(folder_ids)}
    note = (
        f"{path}: {entries} entries for the {entries} scans {folder_ids[0]}..{folder_ids[-1]}, "
        f"all numbered past its end: paired in order (scan {folder_ids[0]} takes the first "
        f"entry), as for a sequence's extract that kept only its own"
    )
    return np.array([position[s] for s in scan_ids], dtype=np.int64), note
