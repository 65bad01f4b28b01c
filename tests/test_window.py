"""The live window over the map and its host store: a whole drive at flat memory, revisits
included (the store alone: tests/test_store.py).

Every test gets its own Taichi runtime (a field of an earlier runtime aborts the process when
used); tisem allows one map per runtime, so a test comparing two maps keeps the first as numpy
arrays (`snapshot()`) and starts a fresh runtime before building the second. Scans are small
hand-built streets (a few thousand labelled points, 20 m range), so a 25 m window evicts and
reloads all the time.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import taichi as ti
from helpers import counters_without_voxel, fresh_runtime

from tisem.config import MapperConfig, RunConfig
from tisem.mapper import Mapper
from tisem.reference import sparse_kernel as kernel_g
from tisem.scan import Scan
from tisem.store import pack

ROAD, SIDEWALK, BUILDING, VEGETATION, POLE = 9, 11, 13, 15, 18


def config(**kw) -> MapperConfig:
    """20 m range, a 25 m window (the least that holds a scan: 20 + 1.2 + 0.8 m)."""
    base = dict(max_range_m=20.0, window_xy_m=25.0, window_z_m=12.0, min_z_m=-4.0, max_z_m=4.0)
    base.update(kw)
    return MapperConfig(**base)


# --------------------------------------------------------------------------- scans


def street(center_xy, rng, n=1500, reach=18.0):
    """World points of a street around center_xy along x: road and sidewalk, a facade, a hedge,
    poles every 5 m. Returns xyz (n, 3), ground-truth train ids (n,)."""
    cx, cy = center_xy
    k = rng.multinomial(n, [0.5, 0.2, 0.2, 0.1])
    g = np.column_stack(
        [
            cx + rng.uniform(-reach, reach, k[0]),
            cy + rng.uniform(-7.5, 7.5, k[0]),
            rng.normal(0, 0.02, k[0]),
        ]
    )
    b = np.column_stack(
        [
            cx + rng.uniform(-reach, reach, k[1]),
            cy + 8.0 + rng.normal(0, 0.03, k[1]),
            rng.uniform(0, 3.5, k[1]),
        ]
    )
    v = np.column_stack(
        [
            cx + rng.uniform(-reach, reach, k[2]),
            cy - 8.0 + rng.uniform(-0.5, 0.5, k[2]),
            rng.uniform(0, 2.5, k[2]),
        ]
    )
    px = np.round((cx + rng.uniform(-reach, reach, k[3])) / 5.0) * 5.0
    p = np.column_stack(
        [
            px + rng.normal(0, 0.05, k[3]),
            cy + 5.0 + rng.normal(0, 0.05, k[3]),
            rng.uniform(0, 3.0, k[3]),
        ]
    )
    labels = np.concatenate(
        [
            np.where(np.abs(g[:, 1] - cy) < 4, ROAD, SIDEWALK),
            np.full(k[1], BUILDING),
            np.full(k[2], VEGETATION),
            np.full(k[3], POLE),
        ]
    ).astype(np.int32)
    return np.concatenate([g, b, v, p]), labels


def scan_at(xyz_sensor, stamp, index, rng, n=1500, noise=0.1, world_shift=(0.0, 0.0, 0.0)):
    """A scan from a sensor at xyz_sensor (world = the scene + world_shift). Input labels are
    the ground truth with a fraction `noise` replaced by random classes."""
    T = np.eye(4)
    yaw = 0.05 * math.sin(index)
    T[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
    T[:3, 3] = np.asarray(xyz_sensor, float) + world_shift
    xyz, gt = street(xyz_sensor[:2], rng, n)
    xyz = xyz + world_shift
    lab = gt.copy()
    flip = rng.random(len(lab)) < noise
    lab[flip] = rng.integers(1, 20, flip.sum())
    return Scan(
        points_sensor=(xyz - T[:3, 3]) @ T[:3, :3],
        T_world_sensor=T,
        stamp_s=stamp,
        labels=lab,
        gt_labels=gt,
        index=index,
        name=f"street {index}",
    )


def drive(xs, seed=0, n=1500, t0=100.0, dt=0.1, world_shift=(0.0, 0.0, 0.0), y=0.0):
    """Scans with the sensor at x = xs[i] (1.7 m up), dt apart."""
    rng = np.random.default_rng(seed)
    return [
        scan_at((x, y, 1.7), t0 + dt * i, i, rng, n, world_shift=world_shift)
        for i, x in enumerate(xs)
    ]


def out_and_back(n_out=8, step_m=10.0):
    """Out along x, step_m per scan, and back over the same ground: every place is left
    (stored) and revisited (reloaded)."""
    xs = [step_m * i for i in range(n_out)]
    return xs + xs[::-1]


# --------------------------------------------------------------------------- comparisons


def assert_same_voxels(a, b, rtol=0.0, atol=0.0):
    """Same voxels, counters, times and lengths (rtol=atol=0: bitwise), same labels."""
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_allclose(a.counts, b.counts, rtol=rtol, atol=atol)
    np.testing.assert_allclose(a.t_last, b.t_last, rtol=0, atol=atol)
    np.testing.assert_allclose(a.ell_m, b.ell_m, rtol=rtol, atol=atol)
    np.testing.assert_array_equal(a.labels(), b.labels())
    assert (a.centroids is None) == (b.centroids is None)
    if a.centroids is not None:  # (class centroids travel with their voxels)
        np.testing.assert_allclose(a.centroids, b.centroids, rtol=rtol, atol=atol)


def subset(snap, rows):
    return snap.subset(rows)


def rows_of(snap, keys):
    """Indices of the given keys in a snapshot (all must be there)."""
    order = np.argsort(pack(snap.keys))
    pos = order[np.searchsorted(pack(snap.keys)[order], pack(keys))]
    np.testing.assert_array_equal(snap.keys[pos], keys)
    return pos


def map_drive(cfg, scans, check=None):
    """Integrate the scans in a fresh map; returns the mapper and the integration reports."""
    mapper = Mapper(cfg)
    reports = []
    for s in scans:
        reports.append(mapper.integrate(s))
        if check is not None:
            check(mapper)
    return mapper, reports


# --------------------------------------------------------------------------- window and store


def test_evict_and_reload_round_trip_exactly(taichi_cpu):
    cfg = config()
    mapper = Mapper(cfg)
    home = drive([0.0, 1.0], seed=3)
    for s in home:
        mapper.integrate(s)
    before = mapper.snapshot()
    assert mapper.stored_voxels == 0 and mapper.live_voxels == len(before) > 1000

    # 300 m away: every voxel of home leaves the field for the store, untouched
    away = drive([300.0], seed=4, t0=101.0)[0]
    rep = mapper.integrate(away)
    assert rep.evicted_voxels == len(before)
    assert mapper.stored_voxels == len(before)
    snap = mapper.snapshot()
    assert_same_voxels(subset(snap, rows_of(snap, before.keys)), before)
    # and queries answer from the store
    centres = before.centers()
    labels, probs = mapper.query(centres)
    np.testing.assert_array_equal(labels, before.point_labels(centres))
    np.testing.assert_allclose(probs, before.probabilities(), rtol=0, atol=1e-7)

    # back home with an empty scan: the voxels return to the field exactly as they left
    T = home[0].T_world_sensor
    empty = Scan(np.zeros((0, 3)), T, 102.0, labels=np.zeros(0, np.int32), index=9)
    rep = mapper.integrate(empty)
    assert rep.reloaded_voxels == len(before)
    assert mapper.live_voxels == len(before)
    live = mapper.live_snapshot()  # only what the Taichi field holds
    np.testing.assert_array_equal(live.keys, before.keys)
    np.testing.assert_array_equal(live.counts, before.counts)  # counters
    np.testing.assert_array_equal(live.t_last, before.t_last)
    np.testing.assert_array_equal(live.ell_m, before.ell_m)  # lengths


def test_compact_counters_live_and_leave_with_their_voxel(taichi_cpu):
    """compact_counters, out and back with a window that holds one scan: voxels leave, their
    blocks are freed and their storage reused, and come back from the store. After every scan
    no counters are allocated where no voxel is live (counters left behind would keep memory
    and hand their stale evidence to the next voxel in that cell), and the map equals the
    default layout's in a window that never evicts, bit for bit."""
    scans = drive(out_and_back(n_out=6), seed=5)
    small, _ = map_drive(config(compact_counters=True), scans, check=assert_counters_with_voxels)
    assert small.stored_voxels > 0
    got = small.snapshot()
    fresh_runtime()
    whole, _ = map_drive(config(window_xy_m=200.0), scans)
    assert whole.stored_voxels == 0
    assert_same_voxels(got, whole.snapshot())


def assert_counters_with_voxels(mapper):
    assert mapper.live_voxels > 0
    assert counters_without_voxel(mapper._fields) == 0


def test_points_on_voxel_faces_find_the_same_voxel_live_and_stored(taichi_cpu):
    """A query point exactly on a voxel face lands in the same voxel whether that voxel is live
    (the kernel floors float32 local coordinates) or stored (the host looks it up): both read
    one float32 local array, so the answers agree point for point."""
    cfg = config()
    mapper = Mapper(cfg)
    for s in drive([0.0, 1.0], seed=3):
        mapper.integrate(s)
    snap = mapper.snapshot()
    corner = snap.keys.astype(np.float64) * cfg.resolution_m  # lower corners, world metres
    half = cfg.resolution_m / 2
    faces = np.concatenate(
        [corner, corner + [half, half, 0.0], corner + [0.0, half, half], corner + [half, 0.0, half]]
    )
    live_labels, live_probs = mapper.query(faces)
    assert mapper.stored_voxels == 0
    mapper.integrate(drive([300.0], seed=4, t0=101.0)[0])  # everything goes to the store
    assert mapper.stored_voxels == len(snap)
    stored_labels, stored_probs = mapper.query(faces)
    np.testing.assert_array_equal(stored_labels, live_labels)
    # (the kernel normalises in float32, the store's path in float64)
    np.testing.assert_allclose(stored_probs, live_probs, rtol=0, atol=1e-6)


@pytest.mark.slow
def test_small_window_equals_window_holding_everything(taichi_cpu):
    """Out 40 m and back at 10 m per scan with a 25 m window (everything leaves and comes back)
    gives the same map as a 64 m window that never evicts: labels and queries identical,
    counters, times and lengths within float rounding (no kernel has float atomics and a
    scan's points are summed in one order, but the two window sizes compile to two kernels,
    whose fast-math sums may round differently: in practice the maps come out bitwise equal)."""
    scans = drive(out_and_back(5, 10.0), seed=5)
    small, reps = map_drive(config(), scans)
    assert sum(r.evicted_voxels for r in reps) > 0 and sum(r.reloaded_voxels for r in reps) > 0
    assert small.stored_voxels > 0
    snap_small = small.snapshot()
    q = np.concatenate([snap_small.centers(), scans[0].points_world()])
    q_small = small.query(q)
    # points in no voxel (0.1-0.35 m off a voxel's centre, most above it) well outside the
    # small window, between stored voxels: the continuous map's blend there too
    rng = np.random.default_rng(5)
    res = small.config.resolution_m
    centres = snap_small.centers()
    off = np.c_[rng.uniform(-0.1, 0.1, (len(centres), 2)), rng.uniform(0.1, 0.35, len(centres))]
    between = centres + off
    st = small.window.state
    local = np.floor(between / res).astype(np.int64) - small.origin_vox
    reach = int(np.ceil(small.config.query_radius_m / res)) + 1
    far = np.any(np.abs(local - st.center_vox) > st.half_vox + reach, axis=1)
    in_voxel = {tuple(k) for k in snap_small.keys}
    free = np.array([tuple(k) not in in_voxel for k in np.floor(between / res).astype(np.int64)])
    between = between[far & free][:2000]
    assert len(between) > 500
    b_small = small.query(between)
    del small

    fresh_runtime()
    big, reps = map_drive(config(window_xy_m=64.0), scans)
    assert sum(r.evicted_voxels for r in reps) == 0 and big.stored_voxels == 0
    snap_big = big.snapshot()
    assert_same_voxels(snap_small, snap_big, rtol=1e-5, atol=1e-6)
    labels, probs = big.query(q)
    np.testing.assert_array_equal(q_small[0], labels)
    # voxel centres: same answer from field and store; raw points may differ in the last bit of
    # the probability (the field's kernel divides in float32 like numpy, in another order)
    np.testing.assert_allclose(q_small[1], probs, rtol=0, atol=1e-6)
    # the blend: the field's kernel samples g from a table, the host computes it
    b_big = big.query(between)
    assert (b_big[0] > 0).mean() > 0.5
    top = np.sort(b_big[1], axis=1)[:, ::-1]
    clear = top[:, 0] - top[:, 1] > 1e-3
    np.testing.assert_array_equal(b_small[0][clear], b_big[0][clear])
    np.testing.assert_allclose(b_small[1], b_big[1], rtol=0, atol=5e-4)


@pytest.mark.slow
def test_cap_shrinks_the_window_and_the_map_stays_correct(taichi_cpu, caplog):
    scans = drive([4.0 * i for i in range(16)], seed=6)
    ref, _ = map_drive(config(window_xy_m=64.0), scans)
    peak = ref.live_blocks
    want = ref.snapshot()
    q = np.concatenate([want.centers(), scans[-1].points_world()])
    want_q = ref.query(q)
    del ref

    fresh_runtime()
    cap = 3300  # 2/3 of what the drive needs; a scan alone adds ~1000 blocks
    assert peak > 1.5 * cap
    seen = []
    with caplog.at_level(logging.WARNING, logger="tisem.live_window"):
        capped, _ = map_drive(
            config(window_xy_m=64.0, max_live_blocks=cap),
            scans,
            check=lambda m: seen.append((m.live_blocks, int(m.window.half_vox[0]))),
        )
    assert "shrunk" in caplog.text
    assert max(b for b, _ in seen) <= cap
    assert min(h for _, h in seen) < 200  # 64 m = 320 voxels: it did shrink
    assert capped.stored_voxels > 0
    assert_same_voxels(capped.snapshot(), want)
    labels, probs = capped.query(q)
    np.testing.assert_array_equal(labels, want_q[0])
    np.testing.assert_allclose(probs, want_q[1], rtol=0, atol=1e-6)


@pytest.mark.slow
def test_a_shrunk_window_that_jumps_to_open_ground_is_said_to_be_full_again(taichi_cpu, caplog):
    """Shrunk under the cap, then a jump to where nothing is mapped: the live blocks left
    behind still count over the room, but none lies in the full box there, so the window takes
    its full size back with that scan, and says so then; shrunk again later, it warns again."""
    here = drive([4.0 * i for i in range(12)], seed=6)
    there = drive([400.0 + 4.0 * i for i in range(12)], seed=8, t0=here[-1].stamp_s + 20.0)

    def said(text):
        return sum(text in r.getMessage() for r in caplog.records)

    seen = []  # per scan: the window's half-size, the "full" and "shrunk" lines said by then
    with caplog.at_level(logging.INFO, logger="tisem.live_window"):
        map_drive(
            config(window_xy_m=64.0, max_live_blocks=3300),
            here + there,
            check=lambda m: seen.append(
                (int(m.window.half_vox[0]), said("back to its full size"), said("shrunk"))
            ),
        )
    full_half = max(h for h, _, _ in seen)
    jump = len(here)
    assert min(h for h, _, _ in seen[:jump]) < full_half, "the window shrank before the jump"
    assert seen[jump - 1][1:] == (0, 1)
    assert seen[jump] == (full_half, 1, 1), "full again with the jump, and said so"
    assert min(h for h, _, _ in seen[jump + 1 :]) < full_half
    assert seen[-1][1:] == (1, 2), "shrunk again later: a second warning"


@pytest.mark.slow
def test_cap_too_small_for_the_scans_cuts_them_and_a_map_that_cannot_fit_is_refused(
    taichi_cpu, tmp_path, caplog
):
    from tisem.pipeline import run_pipeline

    scans = drive([0.0, 1.0, 2.0], seed=7)
    # a scan alone needs ~1000 blocks: each keeps the points in live blocks and in the nearest
    # new blocks it has room for, with one warning line; the cap holds and nothing is skipped
    with caplog.at_level(logging.WARNING, logger="tisem.mapper"):
        result = run_pipeline(
            scans,
            RunConfig(mapper=config(max_live_blocks=50)),
            tmp_path,
            progress=False,
            write_outputs=False,
        )
    assert result.metrics["scans"] == 3 and not result.metrics["skipped"]
    assert caplog.text.count("too dense for the block cap") == 3
    mapper = result.mapper
    assert 0 < mapper.live_blocks <= 50
    # a saved map with more blocks around the sensor than a smaller cap takes is refused
    before, state = mapper.snapshot(), mapper.state()
    fresh_runtime()
    small = Mapper(config(max_live_blocks=10))
    with pytest.raises(ValueError, match="raise max_live_blocks"):
        small.restore(before, state)


@pytest.mark.slow
def test_far_origin_jumps_and_refusal(taichi_cpu):
    """A drive 500 km from the world origin (UTM-like), a bad fix 5 km away and back, and one
    300 km away: maps without a crash or a wrapped index; the 300 km scan is refused clearly."""
    utm = (500_000.0, 5_000_000.0, 80.0)
    scans = drive([0.0, 1.0, 2.0, 5000.0, 5001.0, 3.0], seed=8, world_shift=utm)
    mapper = Mapper(config())
    for s in scans[:3]:
        mapper.integrate(s)
    home = mapper.snapshot()
    assert np.all(np.abs(home.keys[:, 0] * home.resolution_m - utm[0]) < 30)
    for s in scans[3:5]:  # the bad fix: 5 km east
        mapper.integrate(s)
    assert mapper.stored_voxels == len(home)
    empty = Scan(
        np.zeros((0, 3)),
        scans[2].T_world_sensor,
        scans[4].stamp_s + 0.1,
        labels=np.zeros(0, np.int32),
        index=9,
    )
    mapper.integrate(empty)  # back home: home is live again, untouched
    snap = mapper.snapshot()
    x = snap.keys[:, 0] * snap.resolution_m - utm[0]
    assert np.all((np.abs(x) < 30) | (np.abs(x - 5000) < 30))  # nothing anywhere else
    assert_same_voxels(subset(snap, np.flatnonzero(np.abs(x) < 30)), home)
    assert mapper.live_voxels == len(home)
    mapper.integrate(scans[5])  # and mapping goes on there
    near = np.concatenate([s.points_world() for s in (scans[:3] + scans[5:])])
    assert (mapper.query(near)[0] > 0).mean() > 0.95  # live
    assert (mapper.query(scans[4].points_world())[0] > 0).mean() > 0.95  # 5 km away: stored

    bad = drive([300_000.0], seed=9, t0=101.0, world_shift=utm)[0]
    whole = mapper.snapshot()
    with pytest.raises(ValueError, match="km from the map origin"):
        mapper.integrate(bad)
    assert_same_voxels(mapper.snapshot(), whole)
    labels, _ = mapper.query(bad.points_world())  # far queries: nothing there, no crash
    assert not labels.any()


@pytest.mark.slow
def test_decay_covers_the_time_away(taichi_cpu):
    """A voxel that left and came back decays by exp(-dt/tau) over the whole time since its
    last update, time away included. The return scan is a few labelled points of one class, one
    per voxel, so its evidence is known: sigma0 sum g(d / ell) for that class, 0 for others."""
    tau, c = 5.0, POLE
    # the return's evidence: g(d / ell), uncapped
    cfg = config(tau_s=tau, thin_classes=[], vehicle_classes=[])
    mapper = Mapper(cfg)
    home = drive([0.0], seed=10, t0=100.0, n=4000)[0]
    mapper.integrate(home)
    mapper.integrate(drive([300.0], seed=11, t0=101.0)[0])  # away: home is stored
    before = mapper.snapshot()
    near_home = np.abs(before.keys[:, 0] * 0.2) < 30
    assert mapper.stored_voxels == near_home.sum() == len(before) - mapper.live_voxels
    gx, gy = np.meshgrid(np.arange(2.55, 6.1, 0.5), np.arange(-1.45, 1.6, 0.5))
    p = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, 0.03)])  # on the road
    T = home.T_world_sensor
    mapper.integrate(
        Scan((p - T[:3, 3]) @ T[:3, :3], T, 104.0, labels=np.full(len(p), c, np.int32), index=3)
    )
    after = mapper.snapshot()
    assert mapper.stored_voxels == len(before) - near_home.sum()  # home is back

    rows = rows_of(after, before.keys)
    hit = np.isin(pack(before.keys), pack(np.floor(p / 0.2).astype(np.int64)))
    reached = (after.t_last[rows] == 104.0) & ~hit
    assert reached.sum() > 50
    r0, r1 = np.flatnonzero(reached), rows[reached]
    assert np.all(before.t_last[r0] == 100.0)  # 4 s since, 3 of them in the store
    alpha = np.exp(-(104.0 - before.t_last[r0]) / tau)
    others = np.arange(20) != c
    np.testing.assert_allclose(
        after.counts[r1][:, others],
        alpha[:, None] * before.counts[r0][:, others],
        rtol=1e-6,
        atol=1e-12,
    )
    r = np.linalg.norm(before.centers()[r0, None, :] - p[None], axis=2) / before.ell_m[r0, None]
    g = np.where(r < cfg.kernel_cutoff, kernel_g(r), 0.0).sum(axis=1)
    np.testing.assert_allclose(
        after.counts[r1, c], alpha * before.counts[r0, c] + cfg.sigma0 * g, rtol=1e-5, atol=1e-5
    )
    # voxels it did not reach kept their counters and times (decay is lazy)
    kept = after.t_last[rows] < 104.0
    assert kept.sum() > 100
    np.testing.assert_array_equal(after.counts[rows[kept]], before.counts[kept])
    np.testing.assert_array_equal(after.t_last[rows[kept]], before.t_last[kept])


@pytest.mark.slow
def test_long_drive_benchmark_runs(tmp_path):
    from benchmarks import long_drive

    args = long_drive.parse_args(
        [
            "--scans",
            "12",
            "--every",
            "4",
            "--points-per-ring",
            "64",
            "--start-scans",
            "3",
            "--json",
            str(tmp_path / "r.json"),
            "--png",
            str(tmp_path / "r.png"),
        ]
    )
    r = long_drive.run(args)
    assert [row["scan"] for row in r["rows"]] == [4, 8, 12]
    assert {"rss_mb", "ms_per_scan", "live_voxels", "stored_voxels"} <= set(r["rows"][0])
    assert r["loop_closure"]["first"]["accuracy"] > 0.5
    assert (tmp_path / "r.png").stat().st_size > 0
    assert "| scan |" in long_drive.format_result(r)


def test_window_and_memory_kernels_compile_without_taichi_warnings(monkeypatch, capfd):
    """The kernels that free memory (the window's voxels, blocks and top cells, the memory of
    space seen empty) compile silently: taichi 1.7.4 warns that a deactivation's index is "not
    int32" unless it is cast element by element, and a user saw those warnings at the first
    window move. The offline cache is off, so the kernels are compiled, not loaded."""
    monkeypatch.setenv("TI_OFFLINE_CACHE", "0")
    fresh_runtime()
    try:
        cfg = config(free_space=True, seen_empty_s=1.0)
        mapper = Mapper(cfg)
        reports = [mapper.integrate(s) for s in drive([0.0, 1.0, 2.0, 3.0, 300.0], dt=0.5)]
    finally:
        ti.reset()
    assert reports[-1].evicted_voxels > 0  # the window moved: its kernels ran
    err = capfd.readouterr().err
    assert "TaichiWarning" not in err, err[-2000:]
