"""The run's start-up look-ahead (`tisem.pose_gate.PoseGate`): a single outlier pose, first or
not, costs one scan; a real jump, confirmed by the scan after it, costs none. Pure Python:
scans of one point each, poses along x."""

from __future__ import annotations

import numpy as np
import pytest

from tisem.errors import ScanError, SkippedScan
from tisem.pose_gate import MAX_HELD, Anchor, PoseGate
from tisem.scan import Scan

FAR_M = 300e3  # plausible as a place on Earth, 300 km from the drive


def scan_at(index: int, x: float, stamp: float | None = None, scale: float = 1.0) -> Scan:
    T = np.eye(4)
    T[:3, :3] *= scale
    T[0, 3] = x
    return Scan(
        points_sensor=np.zeros((1, 3)),
        T_world_sensor=T,
        stamp_s=0.1 * index if stamp is None else stamp,
        labels=np.ones(1),
        index=index,
        name=f"scan {index}",
    )


def run_gate(items, gate=None):
    """Every verdict, in order, checking that each item gets exactly one, in stream order,
    and that the gate never holds more than MAX_HELD + 1 scans."""
    gate = gate or PoseGate()
    verdicts = []
    for k, item in enumerate(items):
        verdicts += list(gate.offer(k, item))
        assert gate.held <= MAX_HELD + 1
    verdicts += list(gate.finish())
    assert [v.position for v in verdicts] == list(range(len(items)))
    return verdicts


def refused(verdicts) -> dict[int, str]:
    return {v.item.index: v.reason for v in verdicts if v.reason is not None}


@pytest.mark.parametrize("where", [0, 1, 3, 5], ids=["first", "second", "middle", "last"])
def test_a_single_outlier_costs_one_scan(where):
    xs = [1.0 * i for i in range(6)]
    xs[where] = FAR_M
    verdicts = run_gate([scan_at(i, x) for i, x in enumerate(xs)])
    reasons = refused(verdicts)
    assert list(reasons) == [where]
    assert reasons[where].startswith("pose outlier: the sensor is 300 km from scan ")
    if where == 5:
        assert "no later scan confirms it" in reasons[where]


def test_a_jump_the_next_scan_confirms_costs_nothing():
    xs = [0.0, 1.0, 2.0, 5000.0, 5001.0, 5002.0]  # a relocation, or two drives in one log
    assert refused(run_gate([scan_at(i, x) for i, x in enumerate(xs)])) == {}


def test_agreement_scales_with_the_time_between_scans():
    # 30 m in 0.1 s is too fast; 30 m in 1 s is not
    assert list(refused(run_gate([scan_at(0, 0.0), scan_at(1, 30.0), scan_at(2, 1.0)]))) == [1]
    slow = [scan_at(0, 0.0, 0.0), scan_at(1, 30.0, 1.0), scan_at(2, 31.0, 1.1)]
    assert refused(run_gate(slow)) == {}


def test_skipped_scans_and_impossible_poses_keep_their_place():
    # a pose that is no rotation cannot make a Scan: the reader passes on its ScanError as a
    # skipped scan, which keeps its place in the stream like any other
    with pytest.raises(ScanError) as bad:
        scan_at(4, 4.0, scale=2.0)
    items = [
        SkippedScan(0, "scan 0", "truncated"),
        scan_at(1, FAR_M),
        SkippedScan(2, "scan 2", "no labels"),
        scan_at(3, 3.0),
        SkippedScan(4, "scan 4", str(bad.value)),
        scan_at(5, 5.0),
    ]
    reasons = refused(run_gate(items))
    assert list(reasons) == [0, 1, 2, 4]
    assert reasons[0] == "truncated" and reasons[2] == "no labels"
    assert "scaled by 2" in reasons[4]


def test_one_scan_or_scans_that_never_agree_map_from_the_first():
    assert refused(run_gate([scan_at(0, 7.0)])) == {}
    apart = [scan_at(i, 1000.0 * i) for i in range(MAX_HELD + 3)]
    reasons = refused(run_gate(apart))
    mapped = [i for i in range(len(apart)) if i not in reasons]
    assert len(mapped) == 1 and all("pose outlier" in r for r in reasons.values())


def test_a_resumed_gate_goes_on_from_its_anchor():
    anchor = Anchor(9, np.array([9.0, 0.0, 0.0]), 0.9)
    reasons = refused(
        run_gate([scan_at(10, 10.0), scan_at(11, FAR_M), scan_at(12, 12.0)], PoseGate(anchor))
    )
    assert list(reasons) == [11] and "from scan 12's position" in reasons[11]
