"""The same scans make the same map, bit for bit, whatever the two threads' timing: the order
of a scan's points and training rows is fixed by the scan, so free space casts the same rays
and a voxel's points are summed in the same order."""

import dataclasses

import numpy as np
import pytest
from helpers import check_scan_orders, fresh_runtime

from tisem.config import MapperConfig
from tisem.mapper import Mapper
from tisem.synth.sequence import SyntheticSequence, to_scan
from tisem.trace import IntegrationTrace

SCANS = 6  # the street with movers: free space differed by the fourth scan or so


@pytest.fixture(scope="module")
def street():
    """Full-size synthetic scans (tens of thousands of points: both threads take part in every
    loop), movers in them, their motion withheld so that free space has to find it."""
    frames = SyntheticSequence(SCANS, seed=0, movers=True)
    return [dataclasses.replace(to_scan(f), moving=None) for f in frames]


def map_of(scans, trace=None):
    """A fresh runtime (2 threads) and a free-space map of the scans: its voxels sorted by
    key, and each scan's dynamic flags."""
    fresh_runtime()
    mapper = Mapper(MapperConfig(free_space=True))
    flags = [mapper.integrate(s, trace=trace).dynamic for s in scans]
    snap = mapper.snapshot()
    order = np.lexsort(snap.keys.T[::-1])
    fields = {k: v[order] for k, v in vars(snap).items() if isinstance(v, np.ndarray)}
    return fields, flags


def test_a_scan_orders_its_points_and_rows_by_table_cell(street):
    trace = IntegrationTrace()
    map_of(street[:2], trace)
    for k, step in enumerate(trace.scans):
        assert step.kept.sum() > 20_000, "a scan this test is for: both threads share its loops"
        check_scan_orders(step, f"scan {k}")


def test_the_same_scans_make_the_same_map_with_free_space(street):
    first, first_flags = map_of(street)
    again, again_flags = map_of(street)
    assert sum(f.sum() for f in first_flags) > 0, "free space flags some movers"
    for k, (a, b) in enumerate(zip(first_flags, again_flags)):
        np.testing.assert_array_equal(a, b, err_msg=f"dynamic flags of scan {k}")
    assert first.keys() == again.keys()
    for name in first:
        np.testing.assert_array_equal(first[name], again[name], err_msg=name)
