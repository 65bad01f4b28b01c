"""Damaged SemanticKITTI folders: a small intact sequence to start from, and seeded mutations.

Mutations edit one file of a copy of the folder: `.bin` and `.label` files cut short,
extended, emptied, removed or flipped; junk in `poses.txt`, `calib.txt` and `times.txt`
(tokens, lines deleted or doubled, NaN, 1e300, rotations that are no rotations, a second
`Tr:`); files missing or added. Each says whether a reader can detect it: a flipped bit in a
point, or a pose line lost in the middle of `poses.txt` (every later scan takes the next
pose), leave files that are still well-formed.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

N_SCANS, N_POINTS = 4, 30
# a KITTI-like calibration: camera x = -lidar y, camera y = -lidar z, camera z = lidar x
TR = np.array([[0, -1, 0, 0.0], [0, 0, -1, -0.08], [1, 0, 0, -0.27]])
_RAW_IDS = np.array([10, 40, 44, 48, 50, 70, 80, 81], np.uint32)


def _row(T: np.ndarray) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(T)[:3].ravel())


def write_base(folder: Path) -> Path:
    """A sequence folder: 4 scans of 30 points, labels, predictions, poses, calib, times."""
    rng = np.random.default_rng(3)
    for sub in ("velodyne", "labels", "predictions"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    poses = []
    for k in range(N_SCANS):
        points = np.column_stack([rng.uniform(-20, 20, (N_POINTS, 3)), rng.random(N_POINTS)])
        points.astype("<f4").tofile(folder / "velodyne" / f"{k:06d}.bin")
        gt = rng.choice(_RAW_IDS, N_POINTS)
        (gt | (np.uint32(k) << np.uint32(16))).astype("<u4").tofile(
            folder / "labels" / f"{k:06d}.label"
        )
        pred = np.where(rng.random(N_POINTS) < 0.2, rng.choice(_RAW_IDS, N_POINTS), gt)
        pred.astype("<u4").tofile(folder / "predictions" / f"{k:06d}.label")
        c, s = np.cos(0.1 * k), np.sin(0.1 * k)
        poses.append(np.array([[c, 0, s, 0.5 * k], [0, 1, 0, 0.0], [-s, 0, c, 1.5 * k]]))
    (folder / "poses.txt").write_text("".join(_row(P) + "\n" for P in poses))
    (folder / "calib.txt").write_text(
        "".join(f"P{i}: {_row(np.eye(4))}\n" for i in range(4)) + f"Tr: {_row(TR)}\n"
    )
    (folder / "times.txt").write_text("".join(f"{0.1 * k:.6e}\n" for k in range(N_SCANS)))
    return folder


@dataclass
class Mutation:
    """One damaged folder: what was done, whether it can be detected, and how to do it."""

    what: str
    detectable: bool
    edit: Callable[[Path], None]

    def write(self, base: Path, folder: Path) -> None:
        shutil.copytree(base, folder)
        self.edit(folder)


def _pick(rng: np.random.Generator, items):
    return items[int(rng.integers(len(items)))]


def _resize(path: Path, delta: int) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) + delta] if delta < 0 else data + bytes(delta))


def _scan_file(rng, folder: str, suffix: str) -> str:
    return f"{folder}/{int(rng.integers(N_SCANS)):06d}.{suffix}"


def _binary_file(rng) -> Mutation:
    name = _pick(rng, ["velodyne", "predictions", "labels"])
    rel = _scan_file(rng, name, "bin" if name == "velodyne" else "label")
    point = 16 if name == "velodyne" else 4  # bytes per point
    what, delta = _pick(
        rng,
        [
            ("cut by 1 byte", -1),
            ("cut by one value", -4),
            ("cut by one point", -point),
            ("extended by 1 byte", 1),
            ("extended by one point", point),
            ("emptied", "empty"),
            ("removed", "remove"),
            ("a bit flipped", "flip"),
        ],
    )

    def apply(folder: Path) -> None:
        path = folder / rel
        if delta == "remove":
            path.unlink()
        elif delta == "flip":
            data = bytearray(path.read_bytes())
            data[len(data) // 3] ^= 0x10
            path.write_bytes(bytes(data))
        elif delta == "empty":
            path.write_bytes(b"")
        else:
            _resize(path, delta)

    # a flipped bit in a point or a label is another valid value; a removed scan file takes
    # its scan out of the sequence, which no reader can tell from a shorter drive
    detectable = delta != "flip" and not (delta == "remove" and name == "velodyne")
    return Mutation(f"{rel}: {what}", detectable, apply)


def _edit_line(path: Path, index: int, change: Callable[[str], str | None]) -> None:
    lines = path.read_text().splitlines(keepends=True)
    index %= len(lines)
    new = change(lines[index])
    lines[index : index + 1] = [] if new is None else [new]
    path.write_text("".join(lines))


def _token(line: str, rng, value: str, places: tuple[int, ...] | None = None) -> str:
    tokens = line.split()
    tokens[_pick(rng, places or range(len(tokens)))] = value
    return " ".join(tokens) + "\n"


ROTATION_PLACES = (0, 1, 2, 4, 5, 6, 8, 9, 10)  # of the 12 numbers of a 3x4 pose row
TRANSLATION_PLACES = (3, 7, 11)


def _scaled_rotation(line: str, factor: float) -> str:
    v = np.array(line.split(), float).reshape(3, 4)
    v[:, :3] *= factor
    return " ".join(f"{x:.12e}" for x in v.ravel()) + "\n"


def _mirrored(line: str) -> str:
    v = np.array(line.split(), float).reshape(3, 4)
    v[:, 0] *= -1
    return " ".join(f"{x:.12e}" for x in v.ravel()) + "\n"


def _pose_line(rng) -> Mutation:
    k = int(rng.integers(N_SCANS))
    value = _pick(rng, ["abc", "nan", "inf", "-", "0x10", "1,5"])
    edits = [
        (
            f"a number of line {k + 1} replaced by {value!r}",
            True,
            lambda line: _token(line, rng, value),
        ),
        (
            f"a rotation number of line {k + 1} replaced by 1e300",
            True,
            lambda line: _token(line, rng, "1e300", ROTATION_PLACES),
        ),
        # a pose 1e300 m away is a valid pose to a reader; the mapper refuses it (its range)
        (
            f"a translation of line {k + 1} replaced by 1e300",
            False,
            lambda line: _token(line, rng, "1e300", TRANSLATION_PLACES),
        ),
        (f"line {k + 1} removed", k == N_SCANS - 1, lambda line: None),
        (f"line {k + 1} doubled", False, lambda line: line + line),
        (f"line {k + 1} with a 13th number", True, lambda line: line.rstrip() + " 1.0\n"),
        (f"line {k + 1} with 11 numbers", True, lambda line: " ".join(line.split()[:11]) + "\n"),
        (f"line {k + 1}'s rotation scaled by 1000", True, lambda line: _scaled_rotation(line, 1e3)),
        (f"line {k + 1}'s rotation all zero", True, lambda line: _scaled_rotation(line, 0.0)),
        (f"line {k + 1}'s rotation mirrored", True, _mirrored),
        (f"line {k + 1} with Windows line ends", True, lambda line: line.rstrip("\n") + "\r\n"),
        (f"line {k + 1} with trailing spaces", True, lambda line: line.rstrip("\n") + "   \n"),
        (f"a blank line before line {k + 1}", True, lambda line: "\n" + line),
    ]
    what, detectable, change = _pick(rng, edits)
    return Mutation(
        f"poses.txt: {what}", detectable, lambda folder: _edit_line(folder / "poses.txt", k, change)
    )


def _calib(rng) -> Mutation:
    tr_line = 4
    edits = [
        ("the Tr: line removed", True, lambda line: None),
        ("a number of Tr: replaced by 'x'", True, lambda line: _token(line, rng, "x")),
        ("Tr: scaled by 0.5", True, lambda line: "Tr: " + _scaled_rotation(line[3:], 0.5)),
        (
            "a second, different Tr: line",
            True,
            lambda line: line + "Tr: " + _scaled_rotation(line[3:], -1.0),
        ),
        ("a P0: number replaced by 'x'", True, None),
        ("Windows line ends", True, "crlf"),
    ]
    what, detectable, change = _pick(rng, edits)

    def apply(folder: Path) -> None:
        path = folder / "calib.txt"
        if change == "crlf":
            path.write_text(path.read_text().replace("\n", "\r\n"))
        elif change is None:
            _edit_line(path, 0, lambda line: _token(line, rng, "x"))
        else:
            _edit_line(path, tr_line, change)

    return Mutation(f"calib.txt: {what}", detectable, apply)


def _times(rng) -> Mutation:
    k = int(rng.integers(N_SCANS))
    edits = [
        (f"line {k + 1} replaced by 'abc'", True, lambda line: "abc\n"),
        (f"line {k + 1} replaced by 'nan'", True, lambda line: "nan\n"),
        (f"line {k + 1} replaced by 1e300", True, lambda line: "1e300\n"),
        (f"line {k + 1} removed", k == N_SCANS - 1, lambda line: None),
        (f"line {k + 1} with two numbers", True, lambda line: line.rstrip() + " 0.5\n"),
        (f"a line after line {k + 1}", False, lambda line: line + "9.9\n"),
    ]
    what, detectable, change = _pick(rng, edits)
    return Mutation(
        f"times.txt: {what}", detectable, lambda folder: _edit_line(folder / "times.txt", k, change)
    )


def _files(rng) -> Mutation:
    def alias(folder: Path) -> None:
        shutil.copy(folder / "velodyne" / "000001.bin", folder / "velodyne" / "1.bin")

    edits = [
        ("poses.txt removed", True, lambda f: (f / "poses.txt").unlink()),
        ("calib.txt removed", True, lambda f: (f / "calib.txt").unlink()),
        # without times.txt the reader takes 0.1 s spacing, as the format says
        ("times.txt removed", False, lambda f: (f / "times.txt").unlink()),
        ("predictions/ removed", True, lambda f: shutil.rmtree(f / "predictions")),
        ("labels/ removed", False, lambda f: shutil.rmtree(f / "labels")),
        (
            "velodyne/notes.txt added",
            True,
            lambda f: (f / "velodyne" / "notes.txt").write_text("not a scan"),
        ),
        (
            "velodyne/000000.bin.bak added",
            True,
            lambda f: shutil.copy(f / "velodyne" / "000000.bin", f / "velodyne" / "000000.bin.bak"),
        ),
        (
            "velodyne/000009.bin added (no pose, no labels)",
            True,
            lambda f: shutil.copy(f / "velodyne" / "000000.bin", f / "velodyne" / "000009.bin"),
        ),
        ("velodyne/1.bin added beside 000001.bin", True, alias),
        (
            "poses.txt replaced by binary junk",
            True,
            lambda f: (f / "poses.txt").write_bytes(bytes(range(256))),
        ),
        (
            "poses.txt in UTF-16",
            True,
            lambda f: (f / "poses.txt").write_text(
                (f / "poses.txt").read_text(), encoding="utf-16"
            ),
        ),
    ]
    what, detectable, edit = _pick(rng, edits)
    return Mutation(what, detectable, edit)


MAKERS = (_binary_file, _binary_file, _pose_line, _pose_line, _calib, _times, _files)


def kitti_mutation(rng: np.random.Generator, kind: int) -> Mutation:
    """Mutation number `kind` (cycling over the kinds of damage) with `rng`'s choices."""
    return MAKERS[kind % len(MAKERS)](rng)
