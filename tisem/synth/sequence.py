"""Synthetic labelled LiDAR sequences: stream them, turn them into `Scan`s, write SemanticKITTI.

    for frame in iter_synthetic(20, seed=0):             # a 20 m street drive
        scan = to_scan(frame)
    write_semantickitti("out/seq", 4000, route="loop")    # a 3.9 km loop that revisits its start

Scan i is a function of (seed, route, number of scans, i) only — its own random streams and
the tiles it sees — so `SyntheticSequence(...)[i]` regenerates it without the others. (The
loop's length follows the number of scans, so that the drive ends past its start; the street
does not depend on it.)
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from tqdm import tqdm

from tisem.labels import raw_to_train, train_to_raw
from tisem.scan import Scan
from tisem.synth.lidar import Lidar, rotate
from tisem.synth.movers import StreetMovers
from tisem.synth.noise import NoiseModel, mover_raw_ids
from tisem.synth.scene import World, make_rng, make_route
from tisem.synth.shapes import ShapeSet

log = logging.getLogger(__name__)

SCAN_PERIOD_S = 0.1
ROUTES = ("street", "loop")

# KITTI odometry sequence 08's calibration: the projections P0..P3 and the velodyne -> left
# camera transform Tr, so the written poses exercise a real, non-identity extrinsic.
KITTI08_P = (  # one 3x4 matrix per camera, row by row
    "7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 0.000000000000e+00 "
    "0.000000000000e+00 7.070912000000e+02 1.831104000000e+02 0.000000000000e+00 "
    "0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00",
    "7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 -3.798145000000e+02 "
    "0.000000000000e+00 7.070912000000e+02 1.831104000000e+02 0.000000000000e+00 "
    "0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00",
    "7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 4.688783000000e+01 "
    "0.000000000000e+00 7.070912000000e+02 1.831104000000e+02 1.178601000000e-01 "
    "0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 6.203223000000e-03",
    "7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 -3.334597000000e+02 "
    "0.000000000000e+00 7.070912000000e+02 1.831104000000e+02 1.930130000000e+00 "
    "0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 3.318498000000e-03",
)
KITTI08_TR = np.array(
    [
        -1.857739385241e-03,
        -9.999659513510e-01,
        -8.039975204516e-03,
        -4.784029760483e-03,
        -6.481465826011e-03,
        8.051860151134e-03,
        -9.999466081774e-01,
        -7.337429464231e-02,
        9.999773098287e-01,
        -1.805528627661e-03,
        -6.496203536139e-03,
        -3.339968064433e-01,
    ]
)


def kitti08_tr() -> np.ndarray:
    """(4, 4) velodyne -> left camera transform of KITTI sequence 08."""
    T = np.eye(4)
    T[:3, :4] = KITTI08_TR.reshape(3, 4)
    return T


@dataclass
class SynthFrame:
    """One synthetic scan. Labels are SemanticKITTI raw ids; `instance` is 0 for stuff."""

    index: int
    stamp_s: float
    points: np.ndarray  # (N, 3) float32, LiDAR frame
    remission: np.ndarray  # (N,) float32 in [0, 1]
    gt_raw: np.ndarray  # (N,) uint32 ground truth
    pred_raw: np.ndarray  # (N,) uint32 noisy "network" labels, never 0
    T_world_lidar: np.ndarray  # (4, 4) float64
    instance: np.ndarray  # (N,) uint32 ground-truth instance ids (cars, the person)
    dynamic: np.ndarray | None = None  # (N,) bool: on something that moves (movers=True)


class SyntheticSequence:
    """A synthetic drive as a dataset: `len(seq)`, `seq[i]` (any scan, independently),
    iteration in order (tiles are cached, so this is the fast way through)."""

    def __init__(
        self,
        num_scans: int,
        seed: int = 0,
        route: str = "street",
        points_per_ring: int = 1024,
        movers: bool = False,
    ) -> None:
        if num_scans < 0:
            raise ValueError(f"num_scans must be >= 0, got {num_scans}")
        if route not in ROUTES:
            raise ValueError(f"route must be one of {ROUTES}, got {route!r}")
        if points_per_ring < 16:
            raise ValueError(f"points_per_ring must be >= 16, got {points_per_ring}")
        self.num_scans, self.seed, self.route_kind = num_scans, seed, route
        self.noise_seed = seed  # the label noise's streams (several robots: one each)
        self.world = World(seed, make_route(route, num_scans, seed), movers_lane=movers)
        self.lidar = Lidar(points_per_ring=points_per_ring)
        self.noise = NoiseModel()
        self._T_vehicle_lidar = np.eye(4)
        self._T_vehicle_lidar[2, 3] = self.lidar.mount_height_m
        # more movers (tisem/synth/movers.py) and the parking lane they use (World's
        # movers_lane): off by default, so the street stays as it was
        self.movers = StreetMovers(self.world) if movers else None

    def __len__(self) -> int:
        return self.num_scans

    def __iter__(self) -> Iterator[SynthFrame]:
        return (self.frame(i) for i in range(self.num_scans))

    def __getitem__(self, index: int) -> SynthFrame:
        if not -self.num_scans <= index < self.num_scans:
            raise IndexError(f"scan {index} out of range for {self.num_scans} scans")
        return self.frame(index % self.num_scans)

    def poses(self, indices: ArrayLike | None = None) -> np.ndarray:
        """(n, 4, 4) T_world_lidar of the given scans (default all), without rendering."""
        indices = np.arange(self.num_scans) if indices is None else np.asarray(indices)
        return self.world.vehicle_pose(indices * SCAN_PERIOD_S) @ self._T_vehicle_lidar

    def frame(self, index: int, dynamic: bool = True) -> SynthFrame:
        """Render scan `index`; dynamic=False leaves out the moving car and the person."""
        t = index * SCAN_PERIOD_S
        T = self.poses([index])[0]
        s = self.world.ego_s(t)
        shapes = self.world.static_shapes(s, self.lidar.max_range_m + 30.0)
        if dynamic:
            extra = [self.movers.shapes(t)] if self.movers is not None else []
            shapes = ShapeSet.concat([shapes, self.world.actors(t)] + extra)
        ret = self.lidar.cast(
            shapes,
            lambda xy: self.world.ground_label(xy, s),
            T,
            make_rng(self.seed, "lidar", index),
        )
        gt_train, _ = raw_to_train(ret.label)
        world_points = rotate(ret.points.astype(np.float64), T[:3, :3]) + T[:3, 3]
        mover_raw = mover_raw_ids(ret.label, ret.instance)
        pred_train = self.noise.apply(
            gt_train,
            ret.range_m,
            world_points,
            mover_raw,
            self.noise_seed,
            index,
            make_rng(self.noise_seed, "labels", index),
        )
        moving = None
        if self.movers is not None:
            t_end = (self.num_scans - 1) * SCAN_PERIOD_S
            moving = (mover_raw > 0) | self.movers.dynamic(ret.instance, t, t_end)
        return SynthFrame(
            index=index,
            stamp_s=t,
            points=ret.points,
            remission=ret.remission,
            gt_raw=ret.label,
            pred_raw=train_to_raw(pred_train),
            T_world_lidar=T,
            instance=ret.instance,
            dynamic=moving,
        )


def iter_synthetic(
    num_scans: int, seed: int = 0, route: str = "street", points_per_ring: int = 1024
) -> Iterator[SynthFrame]:
    """Stream a synthetic sequence scan by scan (memory stays bounded)."""
    return iter(SyntheticSequence(num_scans, seed, route, points_per_ring))


def to_scan(frame: SynthFrame) -> Scan:
    """The frame as the mapper's `Scan`: predictions as labels, ground truth as gt_labels."""
    pred, _ = raw_to_train(frame.pred_raw)
    gt, _ = raw_to_train(frame.gt_raw)
    return Scan(
        points_sensor=frame.points,
        T_world_sensor=frame.T_world_lidar,
        stamp_s=frame.stamp_s,
        labels=pred,
        gt_labels=gt,
        index=frame.index,
        name=f"synthetic/{frame.index:06d}",
        gt_moving=frame.dynamic,
    )


# the files of a sequence folder: {folder: pattern} and the text files beside them
SEQUENCE_FILES = {"velodyne": "*.bin", "labels": "*.label", "predictions": "*.label"}
SEQUENCE_TEXTS = ("poses.txt", "calib.txt", "times.txt")


def _sequence_files(folder: Path) -> list[Path]:
    found = [p for sub, pattern in SEQUENCE_FILES.items() for p in (folder / sub).glob(pattern)]
    return found + [folder / name for name in SEQUENCE_TEXTS if (folder / name).is_file()]


def clear_sequence(folder: str | Path) -> int:
    """Remove a SemanticKITTI sequence's files from `folder` (scans, label files, poses,
    calibration, times) and its sub-folders left empty; anything else stays. Returns the
    number of files removed."""
    folder = Path(folder)
    files = _sequence_files(folder)
    for path in files:
        path.unlink()
    for sub in SEQUENCE_FILES:
        if (folder / sub).is_dir() and not any((folder / sub).iterdir()):
            (folder / sub).rmdir()
    return len(files)


def write_semantickitti(
    out_dir: str | Path,
    num_scans: int,
    seed: int = 0,
    route: str = "street",
    points_per_ring: int = 1024,
    progress: bool = True,
    overwrite: bool = False,
) -> Path:
    """Write a synthetic sequence as one SemanticKITTI sequence folder; returns its path.

    Poses go to poses.txt in the left camera frame, pose_cam = Tr T_world_lidar Tr^-1, so a
    reader's T_world_lidar = Tr^-1 pose_cam Tr gets the LiDAR poses back. A folder that holds
    a sequence already is refused (FileExistsError: its scans would mix with the new ones),
    unless `overwrite`, which removes that sequence first (`clear_sequence`).
    """
    out = write_frames(
        out_dir,
        iter_synthetic(num_scans, seed, route, points_per_ring),
        num_scans,
        progress,
        overwrite,
    )
    log.info("wrote %d synthetic scans (%s, seed %d) to %s", num_scans, route, seed, out)
    return out


def write_frames(
    out_dir: str | Path,
    frames: Iterator[SynthFrame],
    total: int | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> Path:
    """Write synthetic frames as one SemanticKITTI sequence folder (`write_semantickitti`)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: is a file, not a folder")
    existing = _sequence_files(out) if out.is_dir() else []
    if existing and not overwrite:
        raise FileExistsError(
            f"{out}: holds a sequence already ({len(existing)} files, e.g. "
            f"{existing[0].relative_to(out)}); give overwrite=True "
            f"(--overwrite) to replace it, or another folder"
        )
    if existing:
        log.info("%s: removing the %d files of the sequence there", out, clear_sequence(out))
    for sub in ("velodyne", "labels", "predictions"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    Tr = kitti08_tr()
    Tr_inv = np.linalg.inv(Tr)
    (out / "calib.txt").write_text(
        "".join(f"P{i}: {p}\n" for i, p in enumerate(KITTI08_P))
        + "Tr: "
        + " ".join(f"{v:.12e}" for v in KITTI08_TR)
        + "\n"
    )
    with open(out / "poses.txt", "w") as poses, open(out / "times.txt", "w") as times:
        for f in tqdm(frames, total=total, disable=not progress, unit="scan", desc="synthetic"):
            name = f"{f.index:06d}"
            np.column_stack([f.points, f.remission]).astype("<f4").tofile(
                out / "velodyne" / f"{name}.bin"
            )
            (f.gt_raw | (f.instance << np.uint32(16))).astype("<u4").tofile(
                out / "labels" / f"{name}.label"
            )
            f.pred_raw.astype("<u4").tofile(out / "predictions" / f"{name}.label")
            pose_cam = Tr @ f.T_world_lidar @ Tr_inv
            poses.write(" ".join(f"{v:.12e}" for v in pose_cam[:3].ravel()) + "\n")
            times.write(f"{f.stamp_s:.6e}\n")
    return out
