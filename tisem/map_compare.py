"""How far a merged map is from the map one serial run over the same scans builds.

serial = serial_snapshot(logs, cfg)                 # one Mapper, every scan in time order
diff = compare_snapshots(merged, serial)            # label agreement, counter differences
"""

from __future__ import annotations

import heapq
from dataclasses import asdict, dataclass

import numpy as np

from tisem.config import RunConfig
from tisem.logs import LogSpec, open_log
from tisem.scan import Scan
from tisem.snapshot import MapSnapshot
from tisem.tiles import pack_keys

__all__ = ["MapDifference", "compare_snapshots", "serial_snapshot", "time_ordered_scans"]


@dataclass
class MapDifference:
    """`a` against `b` over the voxels of either (a voxel only one has counts as a label
    disagreement). Counter differences are |a - b| / max(|b|, 1) per counter."""

    voxels_a: int
    voxels_b: int
    common: int
    label_agreement: float  # share of the union's voxels with the same label
    max_counter_diff: float  # over the common voxels
    mean_counter_diff: float

    def to_dict(self) -> dict:
        return asdict(self)


def compare_snapshots(a: MapSnapshot, b: MapSnapshot) -> MapDifference:
    ka, kb = pack_keys(a.keys), pack_keys(b.keys)
    common, ia, ib = np.intersect1d(ka, kb, assume_unique=True, return_indices=True)
    union = len(ka) + len(kb) - len(common)
    same = int(np.count_nonzero(a.labels()[ia] == b.labels()[ib]))
    if len(common):
        rel = np.abs(a.counts[ia] - b.counts[ib]) / np.maximum(np.abs(b.counts[ib]), 1.0)
        max_diff, mean_diff = float(rel.max()), float(rel.mean())
    else:
        max_diff = mean_diff = 0.0
    return MapDifference(
        len(ka), len(kb), len(common), same / union if union else 1.0, max_diff, mean_diff
    )


def time_ordered_scans(logs: list[LogSpec], input: str = "predictions"):
    """The scans of every log, merged in time order (each log is in time order already),
    read one at a time."""

    def keyed(k: int, spec: LogSpec):
        for n, item in enumerate(open_log(spec, input=input)):
            if isinstance(item, Scan):
                yield (item.stamp_s, k, n), item

    merged = heapq.merge(*(keyed(k, spec) for k, spec in enumerate(logs)), key=lambda p: p[0])
    return (item for _, item in merged)


def serial_snapshot(
    logs: list[LogSpec], cfg: RunConfig, threads: int = 2, arch: str = "cpu"
) -> tuple[MapSnapshot, float, int]:
    """The map of one Mapper over every scan of `logs` in time order, in a fresh Taichi
    runtime of this process: (snapshot, mapping seconds, scans mapped)."""
    import time

    import taichi as ti

    from tisem.backend import init_taichi
    from tisem.mapper import Mapper

    init_taichi(arch, threads=threads)
    mapper = Mapper(cfg.mapper)
    seconds, count = 0.0, 0
    for scan in time_ordered_scans(logs, cfg.input):
        start = time.perf_counter()
        try:
            mapper.integrate(scan)
        except ValueError:  # a scan the mapper refuses is skipped, as a run skips it
            continue
        ti.sync()
        seconds += time.perf_counter() - start
        count += 1
    return mapper.snapshot(), seconds, count
