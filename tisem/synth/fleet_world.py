"""Several vehicles in one synthetic world: their own drives along shared streets.

    write_fleet("data/robots", robots=2, scans=60)     # data/robots/sequences/00, 01

Every robot drives the same procedural street (one world, one seed, one world frame) over its
own stretch of it: robot k starts `stride` metres further along than robot k - 1, so
neighbours share part of their streets; odd robots drive the other way, in the other lane.
They drive one after another (robot k starts `gap_s` after robot k - 1 ends), so their logs
are disjoint in time, as a fleet's logs of one day are. Each robot's label noise has its own
streams. The sequences are written in SemanticKITTI layout with a `world_frame.txt` naming the
shared frame, so that fleet mapping merges them into one map (`tisem.logs`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from tisem.logs import WORLD_FRAME_FILE
from tisem.synth.scene import EGO_LANE_U, OTHER_LANE_U, SPEED_MPS, World, street_route
from tisem.synth.sequence import SCAN_PERIOD_S, SyntheticSequence, SynthFrame, write_frames

log = logging.getLogger(__name__)

__all__ = ["RobotDrive", "fleet_drives", "RobotSequence", "write_fleet"]


@dataclass(frozen=True)
class RobotDrive:
    """One robot's drive: where it starts along the street (m), which way, when (s)."""

    start_s_m: float
    forward: bool
    start_time_s: float
    scans: int

    @property
    def length_m(self) -> float:
        return self.scans * SPEED_MPS * SCAN_PERIOD_S


def fleet_drives(
    robots: int, scans: int, overlap: float = 0.5, gap_s: float = 60.0
) -> list[RobotDrive]:
    """`robots` drives of `scans` scans each, neighbours sharing `overlap` of their street."""
    if robots < 1 or scans < 1 or not 0 <= overlap < 1:
        raise ValueError("need robots >= 1, scans >= 1 and 0 <= overlap < 1")
    length = scans * SPEED_MPS * SCAN_PERIOD_S
    stride = length * (1 - overlap)
    duration = scans * SCAN_PERIOD_S
    return [
        RobotDrive(
            start_s_m=k * stride + (0.0 if k % 2 == 0 else length),
            forward=k % 2 == 0,
            start_time_s=k * (duration + gap_s),
            scans=scans,
        )
        for k in range(robots)
    ]


class RobotWorld(World):
    """The street world as one robot drives it (its arc length, lane and heading)."""

    def __init__(self, seed: int, length_m: float, drive: RobotDrive):
        super().__init__(seed, street_route(seed, length_m))
        self.drive = drive

    def ego_s(self, t: float) -> float:
        step = SPEED_MPS * t
        return self.drive.start_s_m + (step if self.drive.forward else -step)

    def vehicle_pose(self, t: ArrayLike) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        s = np.array([self.ego_s(x) for x in t])
        lane = EGO_LANE_U if self.drive.forward else OTHER_LANE_U
        xy, h = self.route.place(s, np.full(len(t), lane))
        if not self.drive.forward:
            h = h + np.pi
        T = np.zeros((len(t), 4, 4))
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(h), -np.sin(h), np.sin(h), np.cos(h)
        T[:, 2, 2] = T[:, 3, 3] = 1.0
        T[:, :2, 3] = xy
        return T


class RobotSequence(SyntheticSequence):
    """One robot's scans: `SyntheticSequence` on its drive, stamps from its start time."""

    def __init__(
        self,
        drive: RobotDrive,
        robot: int,
        seed: int = 0,
        street_m: float = 0.0,
        points_per_ring: int = 1024,
    ):
        super().__init__(drive.scans, seed, "street", points_per_ring)
        self.world = RobotWorld(seed, max(street_m, drive.start_s_m + drive.length_m), drive)
        self.noise_seed = seed * 1000 + robot + 1
        self.drive = drive

    def frame(self, index: int, dynamic: bool = True) -> SynthFrame:
        f = super().frame(index, dynamic)
        return dataclasses.replace(f, stamp_s=f.stamp_s + self.drive.start_time_s)


def write_fleet(
    out_root: str | Path,
    robots: int,
    scans: int,
    seed: int = 0,
    points_per_ring: int = 1024,
    overlap: float = 0.5,
    progress: bool = True,
) -> list[Path]:
    """Write every robot's drive as `out_root/sequences/NN/`; returns the sequence folders."""
    drives = fleet_drives(robots, scans, overlap)
    street_m = max(d.start_s_m + d.length_m for d in drives)
    folders = []
    for k, drive in enumerate(drives):
        seq = RobotSequence(drive, k, seed, street_m, points_per_ring)
        folder = write_frames(
            Path(out_root) / "sequences" / f"{k:02d}", iter(seq), len(seq), progress
        )
        (folder / WORLD_FRAME_FILE).write_text(f"synthetic-street-seed{seed}\n")
        folders.append(folder)
        log.info(
            "robot %d: %d scans from %.0f m %s, t0 %.0f s -> %s",
            k,
            scans,
            drive.start_s_m,
            "forward" if drive.forward else "backward",
            drive.start_time_s,
            folder,
        )
    return folders
