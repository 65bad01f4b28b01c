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


def seconds_per_scan(seconds: list[float]) -> float | None:
    """A run's time per scan: the median of the scans after the first, which compiles or loads
    the kernels (in a short run its second or more would dominate the median); the first's
    own time where it is the only one."""
    return float(np.median(seconds[1:] or seconds)) if seconds else None


class DropLog:
    """Points a mapped scan lost, and why: logged per scan (when it is more than the routine
    range filter) and totalled for metrics.json."""

    ANOMALIES = {
        "dropped_nonfinite": "non-finite (NaN/inf) points",
        "unknown_raw_ids": "unknown raw ids (mapped to 0)",
        "dropped_far": "implausibly far points (> 1 km)",
        "dropped_band": "points outside the height band (unmapped)",
        "dropped_window": "points outside the map's index window",
        "dropped_dense": "points beyond the block cap",
    }
    COUNTS = (
        "dropped_nonfinite",
        "unknown_raw_ids",
        "dropped_range",
        "dropped_far",
        "dropped_band",
        "dropped_window",
        "dropped_dense",
    )
    # the mapper's own warning gives these with their numbers: recorded here, not logged again
    SAID_BY_THE_MAPPER = ("dropped_dense",)

    def __init__(self, totals: dict | None = None, scans: list[dict] | None = None):
        self.totals = {k: 0 for k in self.COUNTS}
        self.totals.update({k: int(v) for k, v in (totals or {}).items()})
        self.scans: list[dict] = list(scans or [])

    def to_dict(self) -> dict:
        return {"totals": dict(self.totals), "scans": list(self.scans)}

    @classmethod
    def from_dict(cls, saved: dict | None) -> DropLog:
        """The log `to_dict()` saved (None: an empty one); ValueError for counts that are not
        whole numbers >= 0."""
        saved = saved or {}
        if not isinstance(saved, dict):
            raise ValueError(f"progress dropped: expected a mapping, got {saved!r}")
        totals = saved.get("totals") or {}
        scans = saved.get("scans") or []
        if (
            not isinstance(totals, dict)
            or not isinstance(scans, list)
            or not all(isinstance(s, dict) for s in scans)
        ):
            raise ValueError(
                "progress dropped: expected totals {kind: count} and a list of per-scan records"
            )
        for kind, count in totals.items():
            if isinstance(count, bool) or not isinstance(count, int) or count < 0:
                raise ValueError(f"progress dropped {kind}: {count!r} is not a count >= 0")
        return cls(totals, scans)

    def add(self, scan: Scan, report: IntegrationReport) -> None:
        """Count what `Mapper.integrate` (its `IntegrationReport`) and the reader dropped."""
        counts = {
            "dropped_nonfinite": report.dropped_nonfinite,
            "unknown_raw_ids": scan.source.unknown_raw_ids if scan.source else 0,
            "dropped_range": report.dropped_range,
            "dropped_far": report.dropped_far,
            "dropped_band": report.dropped_band,
            "dropped_window": report.dropped_window,
            "dropped_dense": report.dropped_dense,
        }
        for k, v in counts.items():
            self.totals[k] += int(v)
        anomalies = {k: int(counts[k]) for k in self.ANOMALIES if counts[k]}
        if anomalies:
            self.scans.append({"index": scan.index, "name": scan.name, **anomalies})
        to_say = {k: v for k, v in anomalies.items() if k not in self.SAID_BY_THE_MAPPER}
        if to_say:
            log.info(
                "scan %s (%s): %s",
                scan.index,
                scan.name,
                ", ".join(f"{v} {self.ANOMALIES[k]}" for k, v in to_say.items()),
            )


@dataclass
class RunProgress:
    """A run's accumulators so far.

    online / input: confusions of the map right after each scan and of the network's own
    labels; seconds: mapping time of each integrated scan; skipped: scans not mapped, in
    order; trajectory: sensor positions of the integrated scans; drops: points lost;
    last_index: `Scan.index` of the last integrated scan (None before the first); indices:
    `Scan.index` of every integrated scan (None: a progress saved without them, where a scan
    up to last_index that was not skipped was mapped).
    """

    online: Confusion
    input: Confusion
    seconds: list[float] = field(default_factory=list)
    skipped: list[SkippedScan] = field(default_factory=list)
    trajectory: list[np.ndarray] = field(default_factory=list)
    drops: DropLog = field(default_factory=DropLog)
    last_index: int | None = None
    indices: list[int] | None = field(default_factory=list)
    _mapped: set[int] = field(default_factory=set, init=False, repr=False, compare=False)

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

    def is_mapped(self, index: int) -> bool:
        """Whether the scan with this `Scan.index` was integrated (the final pass scores
        exactly these)."""
        if self.indices is not None:
            if len(self._mapped) != len(self.indices):
                self._mapped = set(self.indices)
            return index in self._mapped
        return (
            self.last_index is not None and index <= self.last_index and not self.was_skipped(index)
        )

    def add_mapped(self, scan: Scan, seconds: float, report: IntegrationReport) -> None:
        """Record one integrated scan (`report`: what `Mapper.integrate` returned)."""
        self.seconds.append(float(seconds))
        self.drops.add(scan, report)
        self.trajectory.append(scan.T_world_sensor[:3, 3])
        self.last_index = int(scan.index)
        if self.indices is not None:
            self.indices.append(int(scan.index))

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
            "skipped": [
                {"index": int(s.index), "name": str(s.name), "reason": str(s.reason)}
                for s in self.skipped
            ],
            "trajectory": [np.asarray(t, np.float64).tolist() for t in self.trajectory],
            "dropped": self.drops.to_dict(),
            "indices": None if self.indices is None else [int(i) for i in self.indices],
        }

    @classmethod
    def from_dict(cls, saved: dict, num_classes: int) -> RunProgress:
        """The progress `to_dict()` saved; ValueError (naming the entry) when anything in it
        is not what a run can have written: confusions of another class count or with
        negative counts, times or positions that are not finite, a last_index that is not a
        scan number, lists of different lengths."""
        if not isinstance(saved, dict):
            raise ValueError(f"progress: expected a mapping, got {type(saved).__name__}")
        confusions = []
        for name in ("online", "input"):
            matrix = saved.get(name)
            try:
                conf = (
                    Confusion(num_classes)
                    if matrix is None
                    else Confusion.from_matrix(np.asarray(matrix))
                )
            except (ValueError, TypeError) as exc:
                raise ValueError(f"progress {name} confusion: {exc}") from None
            if conf.num_classes != num_classes:
                raise ValueError(
                    f"{name} confusion of shape {conf.matrix.shape}, expected {num_classes} classes"
                )
            confusions.append(conf)
        seconds = _floats(saved.get("seconds", []), "seconds", minimum=0.0)
        trajectory = _positions(saved.get("trajectory", []))
        if len(trajectory) != len(seconds):
            raise ValueError(f"progress: {len(seconds)} scan times but {len(trajectory)} positions")
        indices = saved.get("indices")
        if indices is not None:
            indices = [_scan_index(i, "indices") for i in _list(indices, "indices")]
            if len(indices) != len(seconds):
                raise ValueError(
                    f"progress: {len(seconds)} scan times but {len(indices)} scan indices"
                )
        last = saved.get("last_index")
        last = None if last is None else _scan_index(last, "last_index")
        return cls(
            *confusions,
            seconds=seconds,
            skipped=[_skipped(s) for s in _list(saved.get("skipped", []), "skipped")],
            trajectory=trajectory,
            drops=DropLog.from_dict(saved.get("dropped")),
            last_index=last,
            indices=indices,
        )


def _list(value, name: str) -> list:
    if not isinstance(value, list):
        raise ValueError(f"progress {name}: expected a list, got {type(value).__name__}")
    return value


def _floats(values, name: str, minimum: float) -> list[float]:
    out = []
    for v in _list(values, name):
        if (
            isinstance(v, bool)
            or not isinstance(v, (int, float))
            or not np.isfinite(v)
            or v < minimum
        ):
            raise ValueError(f"progress {name}: {v!r} is not a finite number >= {minimum:g}")
        out.append(float(v))
    return out


def _positions(values) -> list[np.ndarray]:
    out = []
    for v in _list(values, "trajectory"):
        p = np.asarray(v, dtype=object)
        if p.shape != (3,) or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in p
        ):
            raise ValueError(f"progress trajectory: {v!r} is not a finite x y z position")
        out.append(p.astype(np.float64))
    return out


def _scan_index(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"progress {name}: {value!r} is not a scan number (an integer >= 0)")
    return int(value)


def _skipped(entry) -> SkippedScan:
    if not isinstance(entry, dict) or set(entry) != {"index", "name", "reason"}:
        raise ValueError(f"progress skipped: {entry!r} is not an index / name / reason record")
    return SkippedScan(
        _scan_index(entry["index"], "skipped index"), str(entry["name"]), str(entry["reason"])
    )
