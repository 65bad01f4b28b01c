"""The host store alone (tisem/store.py): exact round trips, blocks in pieces, compact payload
kept on disk, a bounded spill file, a full disk survived."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

from tisem.config import MapperConfig
from tisem.mapper import Mapper
from tisem.store import KEY_LIMIT, BlockStore, pack


def random_voxels(rng, n, lo=-300, hi=300, C=20):
    keys = np.unique(rng.integers(lo, hi, (n, 3)), axis=0)
    keys = keys[rng.permutation(len(keys))]
    dense = rng.random((len(keys), C)).astype(np.float32)
    counts = np.where(rng.random((len(keys), C)) < 0.25, dense, 0).astype(np.float32)
    return (
        keys,
        counts,
        rng.random(len(keys)).astype(np.float32),
        rng.random(len(keys)).astype(np.float32),
    )


def sort_rows(arrays):
    order = np.argsort(pack(arrays[0]))
    return [a[order] for a in arrays]


def test_store_round_trip_split_and_lookup():
    rng = np.random.default_rng(0)
    want = random_voxels(rng, 30000)
    store = BlockStore(20)
    west = want[0][:, 0] < 0  # two puts, one block set each
    store.put(*(a[west] for a in want))
    store.put(*(a[~west] for a in want))
    assert len(store) == len(want[0])
    for got, exp in zip(sort_rows(store.arrays()), sort_rows(want)):
        np.testing.assert_array_equal(got, exp)  # exact: keys, counters, t_last, ell

    # a voxel box that cuts blocks: exactly the voxels inside come out, the rest stay
    center, half = np.array([13, -6, 2]), np.array([41, 37, 29])
    inside = np.all(np.abs(want[0] - center) <= half, axis=1)
    assert 0 < inside.sum() < len(inside)
    got = store.take_box(center, half)
    for g, e in zip(sort_rows(got), sort_rows([a[inside] for a in want])):
        np.testing.assert_array_equal(g, e)
    assert len(store) == (~inside).sum()
    counts, found = store.lookup(want[0])
    np.testing.assert_array_equal(found, ~inside)
    np.testing.assert_array_equal(counts[~inside], want[1][~inside])
    assert not counts[inside].any()
    assert store.take_box(center, half) is None

    # the pieces go back (the cut blocks merge again) and everything is as it was
    store.put(*got)
    for g, e in zip(sort_rows(store.arrays()), sort_rows(want)):
        np.testing.assert_array_equal(g, e)
    # taking most of it compacts segments and keeps the rest exact
    big = store.take_box(np.array([0, 0, 0]), np.array([250, 250, 250]))
    rest = ~np.all(np.abs(want[0]) <= 250, axis=1)
    assert len(big[0]) == (~rest).sum() and len(store) == rest.sum()
    for g, e in zip(sort_rows(store.arrays()), sort_rows([a[rest] for a in want])):
        np.testing.assert_array_equal(g, e)


def test_store_refuses_voxels_inside_the_window_and_far_keys():
    rng = np.random.default_rng(1)
    keys, counts, t_last, ell = random_voxels(rng, 100)
    store = BlockStore(20)
    with pytest.raises(ValueError, match="inside the live window"):
        store.put(keys, counts, t_last, ell, box=(keys[0], np.array([2, 2, 2])))
    assert len(store) == 0
    far = np.array([[KEY_LIMIT + 1, 0, 0]])
    with pytest.raises(ValueError, match="beyond"):
        store.put(far, counts[:1], t_last[:1], ell[:1])
    with pytest.raises(ValueError, match="expected"):
        store.put(keys, counts[:, :5], t_last, ell)


def test_store_blocks_in_pieces():
    """A block the window's face cuts is stored in pieces, one per scan; take and lookup gather
    them, and a window sliding over the store takes each voxel exactly once."""
    rng = np.random.default_rng(3)
    want = random_voxels(rng, 20000, lo=-40, hi=40)
    store = BlockStore(20)
    x = want[0][:, 0]
    for cx in range(-41, 41, 3):  # a window sliding +x: voxels leave through its face
        box = (np.array([cx + 200, 0, 0]), np.array([200, 100, 100]))
        leaving = (x >= cx - 3) & (x < cx)
        store.put(*(a[leaving] for a in want), box=box)
    assert len(store) == len(x) and store.num_blocks > len(np.unique(pack(want[0] // 4)))
    counts, found = store.lookup(want[0])
    assert found.all()
    np.testing.assert_array_equal(counts, want[1])
    got = []
    for cx in range(-60, 60, 2):  # and a window coming back takes them out in pieces
        part = store.take_box(np.array([cx, 0, 0]), np.array([1, 100, 100]))
        if part is not None:
            got.append(part)
    assert len(store) == 0
    for g, e in zip(sort_rows([np.concatenate(p) for p in zip(*got)]), sort_rows(want)):
        np.testing.assert_array_equal(g, e)


def clustered_voxels(rng, blocks, per_block, C=20, classes=5):
    """`per_block` distinct random voxels in each of the given blocks, each with `classes` of C
    counters non-zero (as a drive leaves them: ~5 of 20)."""
    local = np.argsort(rng.random((len(blocks), 64)), axis=1)[:, :per_block]
    keys = (
        blocks[:, None, :] * 4 + np.stack([local // 16, local // 4 % 4, local % 4], -1)
    ).reshape(-1, 3)
    nz = np.argsort(rng.random((len(keys), C)), axis=1)[:, :classes]
    counts = np.zeros((len(keys), C), np.float32)
    np.put_along_axis(counts, nz, rng.random(nz.shape).astype(np.float32) + 0.5, axis=1)
    return (
        keys,
        counts,
        rng.random(len(keys)).astype(np.float32),
        rng.random(len(keys)).astype(np.float32),
    )


def street_blocks(rng, n, length=1500):
    """n distinct leaf blocks along a street: long in x, 60 blocks wide, 10 high."""
    blocks = np.unique(
        np.column_stack([rng.integers(0, e, 2 * n) for e in (length, 60, 10)]), axis=0
    )
    return blocks[rng.permutation(len(blocks))[:n]]


def test_store_is_compact():
    """~5 of 20 classes set per voxel, ~8 voxels per block (as in the synthetic loop): the
    store holds well under half of the field's ~100 B per voxel, memory and disk together."""
    rng = np.random.default_rng(2)
    keys, counts, t_last, ell = clustered_voxels(
        rng, np.unique(rng.integers(-2000, 2000, (5000, 3)), axis=0), 8
    )
    store = BlockStore(20)
    store.put(keys, counts, t_last, ell)
    assert (store.nbytes + store.disk_bytes) / len(store) < 45


def test_store_keeps_its_payload_on_disk(tmp_path):
    """Slabs as a drive leaves them (~16 voxels per block, 5 of 20 classes): what the store
    holds in memory, by its own count and by what Python allocated, is a few % of its payload,
    which is in the spill file."""
    import tracemalloc

    rng = np.random.default_rng(5)
    want = clustered_voxels(rng, street_blocks(rng, 20000), 16)
    slabs = [
        np.flatnonzero((want[0][:, 0] >= x) & (want[0][:, 0] < x + 24)) for x in range(0, 6000, 24)
    ]
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        store = BlockStore(20, spill_dir=tmp_path)
        for x, idx in zip(range(0, 6000, 24), slabs):  # a window sliding +x, 24 voxels a scan
            store.put(*(a[idx] for a in want), box=(np.array([x + 524, 0, 0]), np.full(3, 500)))
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    n = len(store)
    assert n == len(want[0])
    print(
        f"per stored voxel: {store.nbytes / n:.2f} B in memory (store.nbytes), "
        f"{held / n:.2f} B allocated, {store.disk_bytes / n:.2f} B on disk"
    )
    assert 30 < store.disk_bytes / n < 40
    assert store.nbytes < 0.05 * store.disk_bytes
    assert held < 0.15 * store.disk_bytes
    assert os.listdir(tmp_path) == []  # the spill file has no name


def test_store_round_trip_through_the_spill_file():
    """Many put / take_box cycles, with small segments, compaction and file rewrites all forced,
    against a plain model of what is stored: every take, lookup and export is exact."""
    rng = np.random.default_rng(6)
    want = clustered_voxels(rng, np.unique(rng.integers(-40, 40, (4000, 3)), axis=0), 10)
    keys = want[0]
    here = np.zeros(len(keys), bool)  # the model: which voxels are stored
    order = np.argsort(pack(keys))

    def rows(k):
        return order[np.searchsorted(pack(keys)[order], pack(k))]

    store = BlockStore(20, rewrite_floor=1 << 14, segment_voxels=3000)
    store.put(*want)  # cut into k-d pieces of <= 3000 voxels
    here[:] = True
    assert store.num_segments > len(keys) / 3000
    for step in range(40):
        center = rng.integers(-150, 150, 3)
        half = rng.integers(10, 110, 3)
        inside = np.all(np.abs(keys - center) <= half, axis=1)
        got = store.take_box(center, half)
        if not (inside & here).any():
            assert got is None
        else:
            r = rows(got[0])
            np.testing.assert_array_equal(np.sort(r), np.flatnonzero(inside & here))
            for g, w in zip(got[1:], want[1:]):
                np.testing.assert_array_equal(g, w[r])
            here[r] = False
        # put some of what is out back: once as a window's evictions, once as a restored map
        back = np.flatnonzero(~here & ~inside & (rng.random(len(keys)) < 0.5))
        store.put(*(a[back] for a in want), box=(center, half) if step % 2 else None)
        here[back] = True
        assert len(store) == here.sum()
        assert store.num_blocks >= len(np.unique(pack(keys[here] // 4)))
        ask = rng.integers(-170, 170, (500, 3))
        ask[:250] = keys[rng.integers(0, len(keys), 250)]
        counts, found = store.lookup(ask)
        m = np.isin(pack(ask), pack(keys[here]))
        np.testing.assert_array_equal(found, m)
        np.testing.assert_array_equal(counts[m], want[1][rows(ask[m])])
        assert not counts[~m].any()
    assert store.spill_rewrites >= 3
    for g, e in zip(sort_rows(store.arrays()), sort_rows([a[here] for a in want])):
        np.testing.assert_array_equal(g, e)
    got = store.take_box(np.zeros(3, int), np.full(3, 1000))
    for g, e in zip(sort_rows(got), sort_rows([a[here] for a in want])):
        np.testing.assert_array_equal(g, e)
    assert len(store) == 0 and store.num_blocks == 0 and store.disk_bytes == 0


@pytest.mark.slow
def test_store_file_stays_bounded():
    """Putting a drive's slabs and taking most of them back, lap after lap: the garbage is
    reclaimed, so the spill file never holds more than ~2x the most ever stored (+ the floor),
    while many times that is written over the laps."""
    rng = np.random.default_rng(7)
    want = clustered_voxels(rng, street_blocks(rng, 6000, length=600), 12)
    x = want[0][:, 0]
    gap = x % 40 > 36  # what the narrow windows below never take: stored once
    floor = 256 << 10
    store = BlockStore(20, rewrite_floor=floor)
    written, most, biggest = 0, 0, 0
    for lap in range(12):
        for x0 in range(0, 2400, 200):
            sel = (x >= x0) & (x < x0 + 200) & (~gap if lap else True)
            before = store.disk_bytes
            store.put(
                *(a[sel] for a in want),
                box=(np.array([x0 + 1200, 0, 0]), np.array([1000, 500, 500])),
            )
            written += store.disk_bytes - before
            most = max(most, store.disk_bytes)
            biggest = max(biggest, store.spill_file_bytes)
            assert store.spill_file_bytes <= max(2 * store.disk_bytes, store.disk_bytes + floor)
        for x0 in range(0, 2400, 40):  # back over it: windows that cut blocks, gaps between
            store.take_box(np.array([x0 + 18, 0, 0]), np.array([18, 500, 500]))
        assert len(store) == gap.sum()
    assert biggest <= 2 * most + floor
    assert written > 3 * (2 * most + floor)  # without the rewrites the file would be this big
    assert store.spill_rewrites > 0


def test_store_refuses_a_missing_spill_dir_and_survives_a_full_disk(tmp_path):
    missing = tmp_path / "no-such-dir"
    with pytest.raises(ValueError, match="no-such-dir"):
        BlockStore(20, spill_dir=missing)
    with pytest.raises(ValueError, match="no-such-dir"):
        # (refused before any Taichi field is made)
        Mapper(MapperConfig(max_range_m=20.0, window_xy_m=25.0, store_dir=str(missing)))

    resource = pytest.importorskip("resource")
    rng = np.random.default_rng(8)
    want = clustered_voxels(rng, street_blocks(rng, 2000, length=200), 10)
    west = want[0][:, 0] < 400
    store = BlockStore(20, spill_dir=tmp_path)
    store.put(*(a[west] for a in want))
    snapshot = sort_rows(store.arrays())
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    # files may not grow past this: the next segments do not fit (EFBIG, as ENOSPC would)
    resource.setrlimit(resource.RLIMIT_FSIZE, (store.spill_file_bytes + 4096, hard))
    try:
        with pytest.raises(OSError, match=re.escape(str(tmp_path))):
            store.put(*(a[~west] for a in want))
        # taking half of a segment compacts it: a write, refused as well
        with pytest.raises(OSError, match=re.escape(str(tmp_path))):
            store.take_box(np.array([200, 120, 20]), np.array([100, 200, 30]))
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert len(store) == west.sum()
    for g, e in zip(sort_rows(store.arrays()), snapshot):
        np.testing.assert_array_equal(g, e)
    store.put(*(a[~west] for a in want))  # and it goes on once there is room
    for g, e in zip(sort_rows(store.arrays()), sort_rows(want)):
        np.testing.assert_array_equal(g, e)
