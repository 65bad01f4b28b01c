"""What a run's metrics.json counts of the points a mapped scan lost (`DropLog`)."""

from __future__ import annotations

import logging

import numpy as np

from tisem.mapper import IntegrationReport
from tisem.progress import DropLog
from tisem.scan import Scan


def a_scan(index: int) -> Scan:
    return Scan(
        points_sensor=np.zeros((4, 3), np.float32),
        T_world_sensor=np.eye(4),
        stamp_s=0.1 * index,
        labels=np.ones(4, np.int32),
        index=index,
        name=f"s{index}",
    )


def test_points_cut_by_the_block_cap_are_counted_but_not_logged_twice(caplog):
    """The mapper warns about a scan too dense for the block cap with its numbers; the drop
    log totals the cut points and lists the scan, without a second line about it."""
    drops = DropLog()
    with caplog.at_level(logging.INFO, logger="tisem.progress"):
        drops.add(a_scan(1), IntegrationReport(points=10, used=3, dropped_dense=7))
        drops.add(
            a_scan(2), IntegrationReport(points=10, used=8, dropped_dense=1, dropped_nonfinite=1)
        )
    assert drops.totals["dropped_dense"] == 8 and drops.totals["dropped_nonfinite"] == 1
    assert drops.scans == [
        {"index": 1, "name": "s1", "dropped_dense": 7},
        {"index": 2, "name": "s2", "dropped_nonfinite": 1, "dropped_dense": 1},
    ]
    assert [r.getMessage() for r in caplog.records] == [
        "scan 2 (s2): 1 non-finite (NaN/inf) points"
    ]
    restored = DropLog.from_dict(drops.to_dict())
    assert restored.totals == drops.totals and restored.scans == drops.scans


def test_a_saved_log_without_the_dense_count_reads_as_zero():
    saved = {"totals": {k: 0 for k in DropLog.COUNTS if k != "dropped_dense"}, "scans": []}
    assert DropLog.from_dict(saved).totals["dropped_dense"] == 0
