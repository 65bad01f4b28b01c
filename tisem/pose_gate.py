"""The run's check that a scan's pose belongs to the drive: one outlier costs one scan.

A pose can pass every test of its own (`tisem.poses.pose_problem`) and still be wrong: 300 km
from every other scan of the drive. The first scan mapped fixes the map's origin, so such a
pose first would get every later good scan refused; in the middle it would drag the live
window away and back. The gate therefore holds a scan whose position does not follow from the
last one it let through, and lets it through only when a later scan confirms it:

* two scans *agree* when their positions are at most `JUMP_SLACK_M + MAX_SPEED_M_S * |dt|`
  apart (dt: their stamps' difference) — no vehicle moves faster;
* at the start nothing has been let through: scans are held until two agree;
* a held scan is let through when a later scan agrees with it (a real jump, or the start), and
  refused as an outlier when a later scan agrees with the last scan let through instead;
* at most `MAX_HELD` scans wait; beyond that the oldest is refused (it agrees with nothing
  around it). At the end of the stream, held scans no later scan confirmed are refused, except
  at the start (a stream of one scan, or of scans that never agree, is mapped from its first).

Scans keep their order: what the gate lets through and refuses comes out in stream order, with
the reader's own skipped scans in their place between them, so a checkpoint written after any
of them holds exactly the stream up to there.

    gate = PoseGate()                     # or PoseGate(anchor) to go on after a checkpoint
    for verdict in gate.offer(k, item):   # item: Scan | SkippedScan, k its stream position
        ...                               # Verdict(k, item, reason): reason None = map it
    for verdict in gate.finish(): ...
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from tisem.errors import SkippedScan
from tisem.scan import Scan

__all__ = ["PoseGate", "Verdict", "Anchor", "MAX_SPEED_M_S", "JUMP_SLACK_M", "MAX_HELD"]

MAX_SPEED_M_S = 100.0  # 360 km/h: faster than any vehicle a LiDAR map is made from
JUMP_SLACK_M = 10.0  # what two poses of (nearly) the same time may differ by: pose noise
MAX_HELD = 4  # scans held at most while waiting for one that agrees


class Verdict(NamedTuple):
    """One item out of the gate: `reason` is None for a scan to map, else why it is refused
    (a `SkippedScan` from the reader comes out with its own reason)."""

    position: int
    item: Scan | SkippedScan
    reason: str | None


@dataclass(frozen=True)
class Anchor:
    """The last scan let through: where and when it was."""

    index: int
    position_m: np.ndarray
    stamp_s: float

    @classmethod
    def of(cls, scan: Scan) -> Anchor:
        return cls(
            int(scan.index), np.asarray(scan.T_world_sensor[:3, 3], np.float64), float(scan.stamp_s)
        )


def _distance(a: Anchor, b: Anchor) -> float:
    return float(np.linalg.norm(a.position_m - b.position_m))


def _allowed_m(a: Anchor, b: Anchor) -> float:
    dt = abs(a.stamp_s - b.stamp_s)
    return JUMP_SLACK_M + MAX_SPEED_M_S * (dt if np.isfinite(dt) else 0.0)


def agree(a: Anchor, b: Anchor) -> bool:
    """Whether two scans' positions can both be right (see the module docstring)."""
    return _distance(a, b) <= _allowed_m(a, b)


def _length(metres: float) -> str:
    return f"{metres / 1000:.4g} km" if metres >= 1000 else f"{metres:.3g} m"


def _outlier(held: Anchor, ref: Anchor, how: str) -> str:
    return (
        f"pose outlier: the sensor is {_length(_distance(held, ref))} from scan "
        f"{ref.index}'s position, {abs(held.stamp_s - ref.stamp_s):.3g} s apart (a vehicle "
        f"moves at most {_length(_allowed_m(held, ref))} in that time); {how}"
    )


Entry = tuple[int, "Scan | SkippedScan"]  # a held scan, or a refused one waiting its turn


class PoseGate:
    """Holds scans whose pose jumps until a later scan confirms or refutes them (see the
    module docstring). `anchor`: the last scan mapped before (a resumed run's)."""

    def __init__(self, anchor: Anchor | None = None):
        self.anchor = anchor
        self._queue: list[Entry] = []

    @property
    def held(self) -> int:
        """Scans waiting for a verdict."""
        return sum(isinstance(item, Scan) for _, item in self._queue)

    def offer(self, position: int, item: Scan | SkippedScan) -> Iterator[Verdict]:
        """Take the next item of the stream; yields the items it decides on, in order."""
        if not self._queue and isinstance(item, SkippedScan):
            yield Verdict(position, item, item.reason)
            return
        self._queue.append((position, item))
        if isinstance(item, Scan):
            yield from self._resolve(Anchor.of(item))

    def finish(self) -> Iterator[Verdict]:
        """The end of the stream: a verdict on every item still held. With nothing let
        through yet, the first held scan is (no scan ever agreed with another)."""
        queue, self._queue = self._queue, []
        for position, item in queue:
            if isinstance(item, SkippedScan):
                yield Verdict(position, item, item.reason)
            elif self.anchor is None or agree(self.anchor, Anchor.of(item)):
                self.anchor = Anchor.of(item)
                yield Verdict(position, item, None)
            else:
                yield Verdict(
                    position,
                    item,
                    _outlier(Anchor.of(item), self.anchor, "no later scan confirms it"),
                )

    # ------------------------------------------------------------------ deciding
    def _resolve(self, newest: Anchor) -> Iterator[Verdict]:
        """The newest held scan confirms the anchor, or another held scan, or neither."""
        if self.anchor is not None and agree(self.anchor, newest):
            yield from self._confirm(
                self.anchor,
                newest,
                f"scans {self.anchor.index} and {newest.index} around it agree with each other",
            )
            return
        for _, item in self._queue[:-1]:
            if isinstance(item, Scan) and agree(Anchor.of(item), newest):
                yield from self._confirm(
                    Anchor.of(item),
                    newest,
                    f"scans {item.index} and {newest.index} agree with each other",
                )
                return
        if self.held > MAX_HELD:
            k, (position, oldest) = next(
                (k, e) for k, e in enumerate(self._queue) if isinstance(e[1], Scan)
            )
            here = Anchor.of(oldest)
            nearest = min(
                (Anchor.of(s) for _, s in self._queue[k + 1 :] if isinstance(s, Scan)),
                key=lambda other: _distance(here, other),
            )
            reason = _outlier(
                here, nearest, f"none of the {MAX_HELD} scans after it agrees with it"
            )
            self._queue[k] = (position, SkippedScan(oldest.index, oldest.name, reason))
            while self._queue and isinstance(self._queue[0][1], SkippedScan):
                position, refused = self._queue.pop(0)
                yield Verdict(position, refused, refused.reason)

    def _confirm(self, a: Anchor, b: Anchor, how: str) -> Iterator[Verdict]:
        """`a` and `b` (the newest) agree: every held scan that agrees with either is let
        through, the others are outliers; `b` becomes the anchor."""
        queue, self._queue = self._queue, []
        for position, item in queue:
            if isinstance(item, SkippedScan):
                yield Verdict(position, item, item.reason)
                continue
            here = Anchor.of(item)
            if agree(here, a) or agree(here, b):
                yield Verdict(position, item, None)
            else:
                yield Verdict(position, item, _outlier(here, b, how))
        self.anchor = b
