"""How far a mapping run has got: everything a checkpoint must hold to continue it exactly.

    progress = RunProgress.start(num_classes=20)
    progress.add_mapped(scan, seconds, report)          # after each integrated scan
    saved = progress.to_dict()                          # plain JSON values
    again = RunProgress.from_dict(saved, num_classes=20)

The map itself is not here: it is the mapper's snapshot and state, saved beside this.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from tisem.errors import SkippedScan
from tisem.evaluate import Confusion
from tisem.scan import Scan

if TYPE_CHECKING:
    from tisem.mapper import IntegrationReport

log = logging.getLogger(__name__)

__all__ = ["DropLog", "RunProgress"]


class DropLog:
    """Points a mapped scan lost, and why: logged per scan (when it is more than the routine
    range filter) and totalled for metrics.json."""

    ANOMALIES = {"dropped_nonfinite": "non-finite (NaN/inf) points",
                 "unknown_raw_ids": "unknown raw ids (mapped to 0)",
                 "dropped_far": "implausibly far points (> 1 km)",
                 "dropped_window": "points outside the map's index window"}
    COUNTS = ("dropped_nonfinite", "unknown_raw_ids", "dropped_range", "dropped_far",
              "dropped_window")

    def __init__(self, totals: dict | None = None, scans: list[dict] | None = None):
        self.totals = {k: 0 for k in self.COUNTS}
        self.totals.update({k: int(v) for k, v in (totals or {}).items()})
        self.scans: list[dict] = list(scans or [])

    def to_dict(self) -> dict:
        return {"totals": dict(self.totals), "scans": list(self.scans)}

    @classmethod
    def from_dict(cls, saved: dict | None) -> DropLog:
        """The log `to_dict()` saved (None: an empty one)."""
        saved = saved or {}
        return cls(saved.get("totals"), saved.get("scans"))

    def add(self, scan: Scan, report: IntegrationReport) -> None:
        """Count what `Mapper.integrate` (its `IntegrationReport`) and the reader dropped."""
        counts = {"dropped_nonfinite": report.dropped_nonfinite,
                  "unknown_raw_ids": scan.source.unknown_raw_ids if scan.source else 0,
                  "dropped_range": report.dropped_range, "dropped_far": report.dropped_far,
                  "dropped_window": report.dropped_window}
        for k, v in counts.items():
            self.totals[k] += int(v)
        anomalies = {k: int(counts[k]) for k in self.ANOMALIES if counts[k]}
        if anomalies:
            self.scans.append({"index": scan.index, "name": scan.name, **anomalies})
            log.info("scan %s (%s): %s", scan.index, scan.name,
                     ", ".join(f"{v} {self.ANOMALIES[k]}" for k, v in anomalies.items()))


@dataclass
class RunProgress:
    """A run's accumulators so far.

    online / input: confusions of the map right after each scan and of the network's own
    labels; seconds: mapping time of each integrated scan; skipped: scans not mapped, in
    order; trajectory: sensor positions of the integrated scans; drops: points lost;
    last_index: `Scan.index` of the last integrated scan (None before the first).
    """

    online: Confusion
    input: Confusion
    seconds: list[float] = field(default_factory=list)
    skipped: list[SkippedScan] = field(default_factory=list)
    trajectory: list[np.ndarray] = field(default_factory=list)
    drops: DropLog = field(default_factory=DropLog)
    last_index: int | None = None

    @classmethod
    def start(cls, num_classes: int) -> RunProgress:
        """Nothing mapped yet."""
        return cls(Confusion(num_classes), Confusion(num_classes))

    @property
    def mapped(self) -> int:
        """Scans integrated so far."""
        return len(self.seconds)

    def was_skipped(self, index: int) -> bool:
        """Whether the scan with this `Scan.index` was skipped (by its reader or the mapper)."""
        return any(s.index == index for s in self.skipped)

    def add_mapped(self, scan: Scan, seconds: float, report: IntegrationReport) -> None:
        """Record one integrated scan (`report`: what `Mapper.integrate` returned)."""
        self.seconds.append(float(seconds))
        self.drops.add(scan, report)
        self.trajectory.append(scan.T_world_sensor[:3, 3])
        self.last_index = int(scan.index)

    def add_skipped(self, skipped: SkippedScan) -> None:
        """Record a scan that was not mapped (the run logs it)."""
        self.skipped.append(skipped)

    def trajectory_array(self) -> np.ndarray:
        """(M, 3) float64 sensor positions of the integrated scans."""
        return np.array(self.trajectory, dtype=np.float64).reshape(-1, 3)

    # ------------------------------------------------------------------ saving
    def to_dict(self) -> dict:
        """Plain JSON values (lists, numbers, strings) that `from_dict` turns back into this."""
        return {
            "last_index": self.last_index,
            "online": self.online.matrix.tolist(),
            "input": self.input.matrix.tolist(),
            "seconds": [float(s) for s in self.seconds],
            "skipped": [{"index": int(s.index), "name": str(s.name), "reason": str(s.reason)}
                        for s in self.skipped],
            "trajectory": [np.asarray(t, np.float64).tolist() for t in self.trajectory],
            "dropped": self.drops.to_dict(),
        }

    @classmethod
    def from_dict(cls, saved: dict, num_classes: int) -> RunProgress:
        """The progress `to_dict()` saved; ValueError when its confusions do not have
        `num_classes` classes."""
        confusions = []
        for name in ("online", "input"):
            matrix = saved.get(name)
            conf = Confusion(num_classes) if matrix is None else Confusion.from_matrix(matrix)
            if conf.num_classes != num_classes:
                raise ValueError(f"{name} confusion of shape {conf.matrix.shape}, expected "
                                 f"{num_classes} classes")
            confusions.append(conf)
        last = saved.get("last_index")
        return cls(*confusions,
                   seconds=[float(s) for s in saved.get("seconds", [])],
                   skipped=[SkippedScan(**s) for s in saved.get("skipped", [])],
                   trajectory=[np.asarray(t, np.float64) for t in saved.get("trajectory", [])],
                   drops=DropLog.from_dict(saved.get("dropped")),
                   last_index=None if last is None else int(last))
