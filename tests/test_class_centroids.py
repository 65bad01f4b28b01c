"""Class centroids: a voxel on a class boundary answers each side with its own class.

An analytic curb (road points on one side of every voxel of a row, sidewalk points on the
other), the slot rule worked by hand, the merge of two maps' slots, and the map file's checks
of what it holds.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import ROAD, fresh_runtime, pose, scan_from_world, small_config

from tisem.class_centroids import CENTROID_COLS, SLOT, merge_slots, split_labels
from tisem.config import MapperConfig
from tisem.io.mapfile import MapFileError, load_map_file, save_map
from tisem.mapper import Mapper
from tisem.merge import merge_snapshots
from tisem.reference import merge_scan_slots
from tisem.snapshot import MapSnapshot

SIDEWALK = 11
RES = 0.2
ROW = 10  # voxels along y


def curb_points(rng) -> tuple[np.ndarray, np.ndarray]:
    """A row of voxels 8 m ahead (x in [8.0, 8.2)): in each, 6 road points at x offsets
    0.02-0.08 m and 4 sidewalk points at 0.12-0.18 m, so road leads with the sidewalk at 4/6."""
    xyz, labels = [], []
    for j in range(ROW):
        for cls, n, lo in ((ROAD, 6, 0.02), (SIDEWALK, 4, 0.12)):
            off = rng.uniform([lo, 0.02, 0.02], [lo + 0.06, 0.18, 0.18], (n, 3))
            xyz.append(np.array([8.0, j * RES, 0.0]) + off)
            labels.append(np.full(n, cls, np.int32))
    return np.concatenate(xyz), np.concatenate(labels)


def curb_queries() -> tuple[np.ndarray, np.ndarray]:
    """One point on each side of every voxel of the row, and the class of its side."""
    y = (np.arange(ROW) + 0.5) * RES
    road = np.stack([np.full(ROW, 8.05), y, np.full(ROW, 0.1)], axis=1)
    sidewalk = road + [0.1, 0.0, 0.0]
    return np.concatenate([road, sidewalk]), np.r_[np.full(ROW, ROAD), np.full(ROW, SIDEWALK)]


def curb_labels(mode: str, **kw) -> np.ndarray:
    rng = np.random.default_rng(3)
    fresh_runtime()
    mapper = Mapper(small_config(mode=mode, **kw))
    for i in range(3):
        xyz, labels = curb_points(rng)
        mapper.integrate(scan_from_world(xyz, pose(), 0.1 * i, labels=labels, index=i))
    return mapper.query(curb_queries()[0], with_probs=False)[0]


@pytest.mark.parametrize("mode", ["csm", "st"])
def test_a_curb_answers_each_side_with_its_class(taichi_cpu, mode):
    _, want = curb_queries()
    np.testing.assert_array_equal(curb_labels(mode), want)


def test_without_centroids_or_below_the_ratio_a_voxel_answers_its_argmax(taichi_cpu):
    """Off, the whole row is road; with centroid_ratio 0.8 the sidewalk's 4/6 is too little
    to split a voxel."""
    assert (curb_labels("csm", class_centroids=False) == ROAD).all()
    assert (curb_labels("csm", centroid_ratio=0.8) == ROAD).all()


def slots(*entries) -> np.ndarray:
    """One row of slots from (class, weight, (x, y, z)) entries."""
    row = np.zeros(CENTROID_COLS)
    for k, (c, w, xyz) in enumerate(entries):
        row[k * SLOT : (k + 1) * SLOT] = [c, w, *xyz]
    return row[None, :]


def test_slot_rule_by_hand():
    """A class in a slot adds up (weighted mean); a new class wears the lighter slot down, or
    takes it when it brings at least that slot's weight; weights decay with the counters."""
    cfg = MapperConfig(mode="adaptive")  # no decay
    held = slots((ROAD, 5.0, (0.05, 0.1, 0.1)), (SIDEWALK, 3.0, (0.15, 0.1, 0.1)))
    same = merge_scan_slots(held, slots((ROAD, 5.0, (0.07, 0.1, 0.1))), np.zeros(1), cfg)
    np.testing.assert_allclose(
        same, slots((ROAD, 10.0, (0.06, 0.1, 0.1)), (SIDEWALK, 3.0, (0.15, 0.1, 0.1)))
    )
    worn = merge_scan_slots(held, slots((1, 2.0, (0.1, 0.1, 0.1))), np.zeros(1), cfg)
    np.testing.assert_allclose(
        worn, slots((ROAD, 5.0, (0.05, 0.1, 0.1)), (SIDEWALK, 1.0, (0.15, 0.1, 0.1)))
    )
    taken = merge_scan_slots(held, slots((1, 3.0, (0.1, 0.1, 0.1))), np.zeros(1), cfg)
    np.testing.assert_allclose(
        taken, slots((ROAD, 5.0, (0.05, 0.1, 0.1)), (1, 3.0, (0.1, 0.1, 0.1)))
    )
    # after tau the sidewalk's 3 have faded to 1.10: the new class's 2 now take its slot
    st = MapperConfig(mode="st", tau_s=1.0)
    decayed = merge_scan_slots(held, slots((1, 2.0, (0.1, 0.1, 0.1))), np.array([1.0]), st)
    np.testing.assert_allclose(
        decayed, slots((ROAD, 5.0 / np.e, (0.05, 0.1, 0.1)), (1, 2.0, (0.1, 0.1, 0.1)))
    )


def test_merging_two_maps_slots():
    """The same class adds up; of up to four classes the two heaviest keep a slot."""
    a = slots((ROAD, 4.0, (0.0, 0.0, 0.0)), (SIDEWALK, 1.0, (0.2, 0.0, 0.0)))
    b = slots((ROAD, 4.0, (0.1, 0.0, 0.0)), (1, 2.0, (0.0, 0.2, 0.0)))
    np.testing.assert_allclose(
        merge_slots(a, b), slots((ROAD, 8.0, (0.05, 0.0, 0.0)), (1, 2.0, (0.0, 0.2, 0.0)))
    )


def test_split_labels_needs_both_classes_in_slots_and_apart():
    counts = np.zeros((3, 20), np.float32)
    counts[:, ROAD], counts[:, SIDEWALK] = 6.0, 4.0
    cent = np.concatenate(
        [
            slots((ROAD, 6.0, (0.05, 0.1, 0.1)), (SIDEWALK, 4.0, (0.15, 0.1, 0.1))),
            slots((ROAD, 6.0, (0.05, 0.1, 0.1)), (1, 4.0, (0.15, 0.1, 0.1))),  # no sidewalk slot
            slots((ROAD, 6.0, (0.1, 0.1, 0.1)), (SIDEWALK, 4.0, (0.1005, 0.1, 0.1))),  # 0.5 mm
        ]
    ).astype(np.float32)
    offsets = np.full((3, 3), 0.1)
    offsets[:, 0] = 0.19
    got = split_labels(counts, cent, offsets, 0.5, np.full(3, ROAD), RES)
    assert got.tolist() == [SIDEWALK, ROAD, ROAD]


def test_map_file_keeps_centroids_and_refuses_damaged_ones(tmp_path):
    snap = MapSnapshot(
        np.array([[40, 0, 0]]),
        np.eye(20, dtype=np.float32)[[ROAD]] * 6,
        np.zeros(1),
        np.full(1, 0.4, np.float32),
        RES,
    )
    snap.centroids = slots((ROAD, 6.0, (0.05, 0.1, 0.1)), (SIDEWALK, 4.0, (0.15, 0.1, 0.1)))
    snap.centroids = snap.centroids.astype(np.float32)
    snap.centroid_ratio = 0.5
    path = save_map(tmp_path / "map.npz", snap, MapperConfig())
    back, _, _ = load_map_file(path)
    np.testing.assert_array_equal(back.centroids, snap.centroids)
    assert back.centroid_ratio == 0.5
    for bad, said in (
        (25.0, "whole number in [0, 20)"),
        (np.nan, "must be finite"),
    ):
        snap.centroids[0, SLOT] = bad
        save_map(path, snap, MapperConfig())
        with pytest.raises(MapFileError) as e:
            load_map_file(path)
        assert said in str(e.value) and "\n" not in str(e.value) and str(path) in str(e.value)
    # a file whose centroids are no numbers at all (written by other code)
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["centroids"] = np.array([["a"] * CENTROID_COLS])
    np.savez(path, **arrays)
    with pytest.raises(MapFileError) as e:
        load_map_file(path)
    assert "must be numbers" in str(e.value) and "\n" not in str(e.value)


def test_merged_maps_fold_their_slots_decayed_like_their_counters():
    """Two maps of one voxel: the older map's slot weights decay by exp(-dt / tau) to the
    newer's time, as its counters do, before the slots fold together."""

    def one_voxel(t_last, cent):
        snap = MapSnapshot(
            np.array([[40, 0, 0]]),
            np.eye(20, dtype=np.float32)[[ROAD]] * 4,
            np.array([t_last]),
            np.full(1, 0.4, np.float32),
            RES,
        )
        snap.centroids, snap.centroid_ratio = cent.astype(np.float32), 0.5
        return snap

    old = one_voxel(0.0, slots((ROAD, 4.0, (0.0, 0.1, 0.1))))
    new = one_voxel(1.0, slots((ROAD, 4.0, (0.1, 0.1, 0.1)), (1, 2.0, (0.15, 0.1, 0.1))))
    merged = merge_snapshots([old, new], 1.0)
    w_old = 4.0 / np.e
    want = slots((ROAD, w_old + 4.0, ((0.4 / (w_old + 4.0)), 0.1, 0.1)), (1, 2.0, (0.15, 0.1, 0.1)))
    np.testing.assert_allclose(merged.centroids, want, rtol=1e-6)
    assert merged.centroid_ratio == 0.5
