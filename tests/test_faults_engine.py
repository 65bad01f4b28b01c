"""Bad input at the engine and the library API: every value refused where it enters (`Scan`,
`Mapper.integrate`, `Mapper.query`, `Mapper.restore`) with one line naming the scan and the
value, the map untouched by what was refused and everything good still mapped.

Dense scans (the block cap within one scan), poses (a bad first pose costs one scan), stamps
(the map's clock), ids and probabilities of any dtype, query points, saved states, and a full
disk under the host store. Small hand-built scenes only.
"""

from __future__ import annotations

import logging
import math
import resource
import signal

import numpy as np
import pytest
from helpers import ROAD, fresh_runtime, pose, scan_from_world, small_config

from tisem.errors import ScanError
from tisem.map_clock import MAX_MAP_SECONDS, ClockState, MapClock, max_step_for
from tisem.mapper import Mapper
from tisem.scan import Scan
from tisem.snapshot import MapSnapshot
from tisem.spill import SpillError
from tisem.store import BlockStore

CAP = 4000  # live leaf blocks: a dense 20 m scan needs ~15,000


def dense_cylinder(n, rng, radius=19.0, z=(-3.5, 3.5)):
    """n sensor-frame points filling the sensor's range cylinder (every block of it)."""
    r = radius * np.sqrt(rng.random(n))
    a = rng.random(n) * 2 * math.pi
    return np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(*z, n)])


def ground_scan(x, stamp, index, rng, n=3000):
    """A normal scan: a labelled road plane around a sensor at (x, 0, 1.7)."""
    T = pose(x, 0.0, 1.7)
    world = np.column_stack(
        [x + rng.uniform(-15, 15, n), rng.uniform(-6, 6, n), rng.normal(0, 0.02, n)]
    )
    return scan_from_world(
        world, T, stamp, labels=np.full(n, ROAD, np.int32), index=index, name=f"road {index}"
    )


def assert_same_map(a: MapSnapshot, b: MapSnapshot, rtol: float = 0.0):
    """Same voxels and values; `rtol` > 0 where the points arrive in another order, which
    changes the order of the float32 atomic adds (last-bit differences, nothing more)."""
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_allclose(a.counts, b.counts, rtol=rtol, atol=0)
    np.testing.assert_array_equal(a.t_last, b.t_last)
    np.testing.assert_allclose(a.ell_m, b.ell_m, rtol=rtol, atol=0)


# --------------------------------------------------------------------------- 1. dense scans


@pytest.mark.slow
def test_a_dense_scan_is_cut_to_the_block_cap_and_later_scans_still_map(taichi_cpu, caplog):
    rng = np.random.default_rng(0)
    mapper = Mapper(small_config(max_live_blocks=CAP))
    pts = dense_cylinder(60_000, rng)
    dense = Scan(
        pts, pose(0, 0, 1.7), 10.0, labels=rng.integers(1, 20, len(pts)), index=0, name="dense"
    )
    from tisem.trace import IntegrationTrace

    trace = IntegrationTrace()
    with caplog.at_level(logging.WARNING, logger="tisem.mapper"):
        rep = mapper.integrate(dense, trace=trace)
    line = [r.getMessage() for r in caplog.records if "block cap" in r.getMessage()]
    assert len(line) == 1
    assert line[0].startswith("scan 0 (dense): too dense for the block cap: its ")
    assert f"4,000 of max_live_blocks={CAP:,} are free" in line[0]
    assert "in the 2,000 nearest new blocks" in line[0]  # half the room: 4000 // 2
    assert 0 < mapper.live_blocks <= CAP // 2
    kept = trace.scans[-1].cut_points
    assert rep.used == len(kept) and rep.dropped_dense > 0
    assert (
        rep.used + rep.dropped_dense + rep.dropped_range + rep.dropped_band + rep.dropped_window
        == len(pts)
    )
    assert f"{rep.used:,} points mapped, {rep.dropped_dense:,} dropped" in line[0]
    # the nearest blocks: every kept point lies closer to the sensor than the ones dropped
    r = np.linalg.norm(pts, axis=1)
    located = (r >= 2.0) & (r <= 20.0)
    dropped = located & ~np.isin(np.arange(len(pts)), kept)
    assert np.percentile(r[kept], 90) < np.percentile(r[dropped], 10)
    cut = mapper.snapshot()
    # normal scans after it map, the cap holds after every one
    for i in range(1, 6):
        mapper.integrate(ground_scan(0.5 * i, 10.0 + 0.1 * i, i, rng))
        assert mapper.live_blocks <= CAP
    assert mapper.scans == 6
    labels, _ = mapper.query(ground_scan(1.0, 11.0, 9, rng).points_world())
    assert (labels == ROAD).mean() > 0.5
    # the cut is exactly the scan of the points it kept
    fresh_runtime()
    again = Mapper(small_config(max_live_blocks=CAP))
    again.integrate(Scan(pts[kept], dense.T_world_sensor, 10.0, labels=dense.labels[kept]))
    assert_same_map(again.snapshot(), cut, rtol=1e-6)


def test_a_dense_scan_with_no_room_left_is_refused_and_the_map_kept(taichi_cpu):
    rng = np.random.default_rng(1)
    mapper = Mapper(small_config(max_live_blocks=2))
    first = dense_cylinder(2000, rng)
    mapper.integrate(Scan(first, pose(0, 0, 1.7), 0.0, labels=np.full(2000, ROAD), index=0))
    assert mapper.live_blocks == 1  # 2 free: half of it
    before = mapper.snapshot()
    far = dense_cylinder(2000, rng, radius=19.0, z=(2.5, 3.5))  # above every live block
    with pytest.raises(
        ValueError,
        match=r"^scan 1: too dense for the block cap: .* only 1 of "
        r"max_live_blocks=2 are free, none of them in a live "
        r"block; skipped$",
    ):
        mapper.integrate(Scan(far, pose(0, 0, 1.7), 0.1, labels=np.full(2000, ROAD), index=1))
    assert_same_map(mapper.snapshot(), before)
    # a scan over the live block still maps there
    mapper.integrate(Scan(first, pose(0, 0, 1.7), 0.2, labels=np.full(2000, ROAD), index=2))
    assert mapper.scans == 2 and mapper.live_blocks == 1


def test_the_first_scan_refused_by_the_cap_leaves_no_origin(taichi_cpu):
    rng = np.random.default_rng(2)
    mapper = Mapper(small_config(max_live_blocks=1))
    pts = dense_cylinder(500, rng)
    with pytest.raises(ValueError, match="too dense for the block cap"):
        mapper.integrate(Scan(pts, pose(5000, 0, 1.7), 0.0, labels=np.full(500, ROAD)))
    assert mapper.origin_vox is None and mapper.t0 is None and mapper.live_voxels == 0


# --------------------------------------------------------------------------- 4-5. poses


def _rot(kind):
    R = np.eye(3)
    if kind == "singular":
        R[2] = 0.0
    elif kind == "scaled":
        R *= 1000.0
    elif kind == "mirrored":
        R[0, 0] = -1.0
    return R


@pytest.mark.parametrize(
    "kind, message",
    [
        ("far 1e30", r"position is 1e\+30 m from the origin"),
        pytest.param("far 1e9", r"position is 1e\+09 m from the origin", marks=pytest.mark.slow),
        ("singular", r"not a rotation \(singular"),
        pytest.param("scaled", r"not a rotation \(scaled by 1000", marks=pytest.mark.slow),
        pytest.param("mirrored", r"not a rotation \(mirrored", marks=pytest.mark.slow),
        pytest.param("nan", "NaN/inf entries", marks=pytest.mark.slow),
    ],
)
def test_a_bad_pose_is_refused_and_the_origin_comes_from_the_first_good_one(
    taichi_cpu, kind, message
):
    rng = np.random.default_rng(3)
    good = [ground_scan(0.5 * i, 0.1 * i, i, rng) for i in range(1, 3)]
    T = pose(0, 0, 1.7)
    if kind.startswith("far"):
        T[0, 3] = float(kind.split()[1])
    elif kind == "nan":
        T[1, 1] = np.nan
    else:
        T[:3, :3] = _rot(kind)
    pts = good[0].points_sensor
    with pytest.raises(ValueError, match=rf"^scan 0 \(bad\): the pose.*{message}"):
        Scan(pts, T, 0.0, labels=good[0].labels, index=0, name="bad")
    # a Scan's pose replaced after it was built: refused by the mapper all the same
    mapper = Mapper(small_config())
    bad = Scan(pts, pose(0, 0, 1.7), 0.0, labels=good[0].labels, index=0, name="bad")
    bad.T_world_sensor = T
    with pytest.raises(ValueError, match=rf"^scan 0 \(bad\): the pose.*{message}"):
        mapper.integrate(bad)
    assert mapper.origin_vox is None and mapper.live_voxels == 0
    for s in good:
        mapper.integrate(s)
    assert mapper.scans == 2
    assert np.abs(mapper.origin_vox * 0.2).max() < 10  # the good scans' origin
    labels, _ = mapper.query(good[1].points_world())
    assert (labels == ROAD).mean() > 0.9


# --------------------------------------------------------------------------- 6. stamps


@pytest.mark.parametrize("stamp", [math.nan, math.inf, -math.inf, 1e30, 1e300, "12.5", True])
def test_a_stamp_that_is_not_a_time_is_refused(stamp):
    # a ScanError (a ValueError): a reader that builds the Scan reports it as a skipped scan
    with pytest.raises(
        ScanError, match=r"^scan 4: stamp_s .*(not a time|number of seconds)"
    ) as refused:
        Scan(np.zeros((2, 3)), np.eye(4), stamp, labels=[1, 1], index=4)
    assert refused.value.index == 4


def test_one_bad_stamp_costs_one_scan_and_leaves_every_time_finite(taichi_cpu):
    rng = np.random.default_rng(4)
    cfg = small_config(mode="st", tau_s=5.0)
    mapper = Mapper(cfg)
    scans = [ground_scan(0.3 * i, 100.0 + 0.1 * i, i, rng) for i in range(4)]
    for s in scans[:2]:
        mapper.integrate(s)
    before = mapper.snapshot()
    jump = ground_scan(0.6, 100.0 + 1e6, 2, rng)  # a glitch a million seconds ahead
    with pytest.raises(
        ValueError,
        match=r"^scan 2 \(road 2\): stamp .* jumps 1e\+06 s after "
        r"the previous scan's; a jump over 23.03 s is taken "
        r"only when the next scan confirms it",
    ):
        mapper.integrate(jump)
    assert_same_map(mapper.snapshot(), before)
    mapper.integrate(scans[2])  # back on time: mapped
    back = ground_scan(0.9, 100.0 - 1e6, 3, rng)  # and one a million seconds behind
    with pytest.raises(ValueError, match="jumps 1e\\+06 s before the previous scan's"):
        mapper.integrate(back)
    mapper.integrate(scans[3])
    snap = mapper.snapshot()
    assert np.isfinite(snap.t_last).all() and np.isfinite(snap.counts).all()
    assert snap.t_last.max() == pytest.approx(100.3) and snap.t_last.min() >= 100.0
    assert mapper.scans == 4


def test_a_real_gap_is_taken_once_the_next_scan_confirms_it(taichi_cpu):
    rng = np.random.default_rng(5)
    mapper = Mapper(small_config(mode="st", tau_s=5.0))
    mapper.integrate(ground_scan(0.0, 10.0, 0, rng))
    with pytest.raises(ValueError, match="jumps 3600 s after"):
        mapper.integrate(ground_scan(0.0, 3610.0, 1, rng))
    mapper.integrate(ground_scan(0.0, 3610.1, 2, rng))  # the gap was real: time goes on
    assert mapper.snapshot().t_last.max() == pytest.approx(3610.1)
    # a clock reset (back by an hour, twice): no time passes, times stay in order
    with pytest.raises(ValueError, match="before the previous scan's"):
        mapper.integrate(ground_scan(0.0, 10.0, 3, rng))
    mapper.integrate(ground_scan(0.0, 10.1, 4, rng))
    assert mapper.snapshot().t_last.max() == pytest.approx(3610.1)
    mapper.integrate(ground_scan(0.0, 10.6, 5, rng))
    assert mapper.snapshot().t_last.max() == pytest.approx(3610.6)


def test_the_map_clock_rules():
    """Out-of-order stamps pass no time; a retried refused scan confirms nothing; the clock
    stops at MAX_MAP_SECONDS; modes without decay take any step."""
    clock = MapClock(5.0)
    assert clock.max_step_s == pytest.approx(5.0 * math.log(100))
    for stamp in (50.0, 50.1, 50.05, 50.2):
        t = clock.time_of(stamp, "s")
        clock.advance(stamp, t)
    assert clock.state.latest_s == pytest.approx(0.2)
    assert clock.time_of(50.05, "s") == pytest.approx(0.2)  # behind: no time passes
    with pytest.raises(ValueError, match="jumps"):
        clock.time_of(900.0, "s")
    with pytest.raises(ValueError, match="jumps"):
        clock.time_of(900.0, "s")  # the same scan again
    late = 50.0 + MAX_MAP_SECONDS + 10
    with pytest.raises(ValueError, match="jumps"):
        clock.time_of(late, "s")
    with pytest.raises(ValueError, match="a map spans at most 1048576 s"):
        clock.time_of(late + 1, "s")
    assert max_step_for(0.0) == max_step_for(math.inf) == math.inf
    assert MapClock(math.inf).time_of(1e9, "s") == 0.0  # not started
    with pytest.raises(ValueError, match="latest_s must be a finite number, got nan"):
        MapClock.from_dict(5.0, {"t0": 1.0, "latest_s": math.nan})
    assert MapClock.from_dict(5.0, {"t0": 1.0}).state == ClockState(t0=1.0)


# --------------------------------------------------------------------------- 6. ids, probs


@pytest.mark.parametrize(
    "labels, message",
    [
        (np.array([1, 2**32 + 9, 3], np.int64), r"got 4294967305 at point 1"),
        (np.array([1, 2**63, 3], np.uint64), r"got 9223372036854775808 at point 1"),
        (np.array([1, -1, 3], np.int8), r"got -1 at point 1"),
        (np.array([1.0, 1e300, 3.0]), r"got 1e\+300 at point 1"),
        (np.array([1.0, 2.5, 3.0]), r"got 2.5 at point 1"),
        (np.array([1.0, np.nan, 3.0]), r"got nan at point 1"),
        (np.array(["1", "2", "3"]), r"must be numbers, got an array of dtype <U1"),
    ],
)
def test_ids_are_checked_before_any_cast(labels, message):
    with pytest.raises(ValueError, match=rf"^scan 7: train ids .*{message}"):
        Scan(np.zeros((3, 3)), np.eye(4), 0.0, labels=labels, index=7)
    with pytest.raises(ValueError, match=rf"^scan 7: ground-truth train ids .*{message}"):
        Scan(np.zeros((3, 3)), np.eye(4), 0.0, labels=[1, 1, 1], gt_labels=labels, index=7)


def test_ids_of_any_integer_dtype_or_whole_floats_are_taken(taichi_cpu):
    rng = np.random.default_rng(6)
    ref = ground_scan(0.0, 0.0, 0, rng)
    for dtype in (np.uint8, np.int16, np.uint32, np.int64, np.uint64, np.float32, np.float64):
        s = Scan(ref.points_sensor, ref.T_world_sensor, 0.0, labels=ref.labels.astype(dtype))
        assert s.labels.dtype == np.int32 and np.array_equal(s.labels, ref.labels)
    mapper = Mapper(small_config())
    # ids past the map's classes, put in after the Scan was built, never wrap either
    ref.labels = np.where(np.arange(len(ref.labels)) == 5, 2**32 + ROAD, ROAD).astype(np.uint64)
    with pytest.raises(
        ValueError,
        match=r"^scan 0 \(road 0\): train ids must be whole numbers "
        r"in \[0, 20\), got 4294967305 at point 5",
    ):
        mapper.integrate(ref)
    ref.labels = np.full(len(ref.labels), 20, np.int32)
    with pytest.raises(ValueError, match=r"in \[0, 20\), got 20 at point 0"):
        mapper.integrate(ref)
    assert mapper.live_voxels == 0 and mapper.origin_vox is None


@pytest.mark.parametrize(
    "value, message",
    [
        (3e38, r"got 3e\+38 at point 2, class 4"),
        (1.5, r"got 1.5 at point 2, class 4"),
        (-0.25, r"got -0.25 at point 2, class 4"),
        (np.nan, r"got nan at point 2, class 4"),
    ],
)
def test_probabilities_are_finite_and_within_0_and_1(value, message):
    probs = np.full((4, 20), 0.05)
    probs[2, 4] = value
    with pytest.raises(
        ValueError,
        match=rf"^scan 1: probabilities must be finite and in "
        rf"\[0, 1\], {message}",
    ):
        Scan(np.ones((4, 3)), np.eye(4), 0.0, probs=probs, index=1)
    # a non-finite point's row is never used: anything there is taken
    pts = np.ones((4, 3))
    pts[2, 0] = np.nan
    assert Scan(pts, np.eye(4), 0.0, probs=probs).probs.dtype == np.float32


def test_probabilities_map_without_overflow(taichi_cpu):
    """Probabilities at the top of the range (1.0, and float16's 1 + 2^-10) map to finite
    counters in every voxel."""
    rng = np.random.default_rng(7)
    s = ground_scan(0.0, 0.0, 0, rng)
    probs = np.zeros((s.num_points, 20), np.float16)
    probs[:, 1:] = 0.5
    probs[:, ROAD] = np.float16(1.0) + np.float16(2**-10)
    mapper = Mapper(small_config(mode="adaptive"))
    for k in range(3):
        mapper.integrate(Scan(s.points_sensor, s.T_world_sensor, 0.1 * k, probs=probs, index=k))
    snap = mapper.snapshot()
    assert len(snap) and np.isfinite(snap.counts).all() and np.isfinite(snap.ell_m).all()
    assert (snap.labels() == ROAD).all()


# --------------------------------------------------------------------------- 6. queries


def test_query_points_of_any_numeric_dtype(taichi_cpu):
    rng = np.random.default_rng(8)
    s = ground_scan(0.0, 0.0, 0, rng)
    mapper = Mapper(small_config())
    mapper.integrate(s)
    world = s.points_world()
    want, _ = mapper.query(world)
    for dtype in (np.float16, np.int16, np.int64, np.uint64, np.longdouble):
        got, probs = mapper.query(world.astype(dtype))
        assert got.shape == (len(world),) and np.isfinite(probs).all()
    assert np.array_equal(mapper.query(world.astype(np.longdouble))[0], want)
    huge = np.array([[1e300, 0, 0], [-1e30, 5e29, 0], [np.nan, 0, 0], [2**63, 0, 0]])
    assert not mapper.query(huge)[0].any()
    for bad in (np.array([["a", "b", "c"]]), world.astype(complex), np.array([[None] * 3])):
        with pytest.raises(ValueError, match="query points must be numbers"):
            mapper.query(bad)
    with pytest.raises(ValueError, match=r"query points must be \(N, 3\)"):
        mapper.query(np.zeros((4, 2)))


# --------------------------------------------------------------------------- saved states


def test_a_saved_state_that_no_mapper_wrote_is_refused(taichi_cpu):
    rng = np.random.default_rng(9)
    mapper = Mapper(small_config())
    for i in range(2):
        mapper.integrate(ground_scan(0.2 * i, 0.1 * i, i, rng))
    snap, state = mapper.snapshot(), mapper.state()
    fresh_runtime()
    fresh = Mapper(small_config())
    bad_states = [
        ({"scans": "abc"}, "scans must be a whole number"),
        ({"scans": -3}, "scans must be a whole number"),
        ({"t0": math.nan}, "t0 must be a finite number"),
        ({"origin_vox": [0, 0]}, "origin_vox must be 3 whole numbers"),
        ({"center_vox": [0, 0, 1e12]}, r"center_vox\[2\] must be a whole number"),
        ({"clock": {"t0": 0.0, "offset_s": "x"}}, "offset_s must be a finite"),
        ({"last_stamp_s": math.inf}, "last_stamp_s must be a finite number"),
    ]
    for change, message in bad_states:
        with pytest.raises(ValueError, match=message):
            fresh.restore(snap, {**state, **change})
    counts = snap.counts.copy()
    counts[3, 2] = np.nan
    bad_snaps = [
        (
            MapSnapshot(snap.keys, counts, snap.t_last, snap.ell_m, 0.2),
            r"counts holds nan at \(3, 2\)",
        ),
        (
            MapSnapshot(snap.keys, -snap.counts, snap.t_last, snap.ell_m, 0.2),
            "counters must be finite and >= 0",
        ),
        (
            MapSnapshot(snap.keys, snap.counts, snap.t_last + 1e300, snap.ell_m, 0.2),
            "a map spans at most",
        ),
        (
            MapSnapshot(snap.keys + 2**22, snap.counts, snap.t_last, snap.ell_m, 0.2),
            "a map holds at most",
        ),
        (
            MapSnapshot(snap.keys, snap.counts[:, :5], snap.t_last, snap.ell_m, 0.2),
            "the mapper has 20 classes",
        ),
        (
            MapSnapshot(snap.keys, snap.counts, snap.t_last, snap.ell_m, 0.3),
            "snapshot resolution 0.3 m != mapper 0.2 m",
        ),
    ]
    for bad, message in bad_snaps:
        with pytest.raises(ValueError, match=message):
            fresh.restore(bad, state)
    assert fresh.origin_vox is None and fresh.stored_voxels == 0 and fresh.live_voxels == 0
    fresh.restore(snap, state)  # and the real one still loads, exactly
    assert_same_map(fresh.snapshot(), snap)


# --------------------------------------------------------------------------- a full disk


class FileSizeLimit:
    """While active, no file of this process may grow past `limit` bytes: writes beyond fail
    with EFBIG, as on a full disk (SIGXFSZ ignored meanwhile)."""

    def __init__(self, limit: int):
        self.limit = limit

    def __enter__(self):
        self._old = resource.getrlimit(resource.RLIMIT_FSIZE)
        self._signal = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (self.limit, self._old[1]))

    def __exit__(self, *exc):
        resource.setrlimit(resource.RLIMIT_FSIZE, self._old)
        signal.signal(signal.SIGXFSZ, self._signal)


def test_a_full_disk_under_the_store_raises_one_error_and_keeps_the_store(tmp_path):
    store = BlockStore(20, spill_dir=str(tmp_path))
    rng = np.random.default_rng(10)
    keys = rng.integers(-500, 500, (20_000, 3))
    keys = np.unique(keys, axis=0)
    counts = rng.random((len(keys), 20)).astype(np.float32)
    store.put(keys, counts, np.zeros(len(keys)), np.full(len(keys), 0.4))
    before = store.arrays()
    with FileSizeLimit(store.spill_file_bytes):
        with pytest.raises(
            SpillError,
            match=rf"host store: could not write its spill file in "
            rf"{tmp_path} \(.*\); set store_dir",
        ):
            store.put(keys + 2000, counts, np.zeros(len(keys)), np.full(len(keys), 0.4))
    after = store.arrays()
    assert len(store) == len(before[0])
    for a, b in zip(before, after):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow
def test_a_full_disk_while_the_window_evicts_leaves_the_map_whole(taichi_cpu, tmp_path):
    """The window's move fails when the store cannot take what leaves it: one SpillError, the
    field and the store exactly as before the move, and mapping goes on once there is room."""
    rng = np.random.default_rng(11)
    scans = [ground_scan(12.0 * i, 0.1 * i, i, rng) for i in range(5)]
    cfg = small_config(window_xy_m=22.0, store_dir=str(tmp_path))
    mapper = Mapper(cfg)
    for s in scans[:3]:  # (the eviction kernels compile here)
        mapper.integrate(s)
    assert mapper.stored_voxels > 0
    before = mapper.snapshot()
    live = mapper.live_snapshot()
    with FileSizeLimit(mapper.store.spill_file_bytes):
        with pytest.raises(SpillError, match="could not write its spill file"):
            mapper.integrate(scans[3])
    assert_same_map(mapper.snapshot(), before)
    assert_same_map(mapper.live_snapshot(), live)
    for s in scans[3:]:
        mapper.integrate(s)
    done = mapper.snapshot()
    fresh_runtime()
    ref = Mapper(small_config(window_xy_m=22.0, store_dir=str(tmp_path)))
    for s in scans:
        ref.integrate(s)
    assert_same_map(done, ref.snapshot())
