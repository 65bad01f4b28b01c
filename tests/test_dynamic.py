"""Free space and moving objects in analytic scenes: a wall at 10 m and a car in front of it.

The occupancy evidence of a voxel follows a closed form: +1 per scan that hits it, -1 per scan
whose rays cross it, both after the decay exp(-dt / tau) since its last change, clamped to
+-occupancy_cap; the voxel is empty at or below -empty_evidence. `scans_to_clear` computes
from it how many scans an object that has left takes to clear, and the map must agree exactly.
"""

import math

import numpy as np
import pytest
from helpers import (
    BUILDING,
    POLE,
    C,
    away_from_faces,
    fresh_runtime,
    pose,
    scan_from_world,
    small_config,
    voxel_keys,
)

from tisem.mapper import Mapper

pytestmark = pytest.mark.slow  # (each test builds and drives its own maps: 10-40 s)

CAR = 1
RES = 0.2
DT = 0.1  # 10 Hz
WALL_X, CAR_X = 10.1, 5.1  # (not on a voxel face)
SPACING = 0.05


def plane_x(x, y_range, z_range):
    ys = np.arange(y_range[0] + SPACING / 2, y_range[1], SPACING)
    zs = np.arange(z_range[0] + SPACING / 2, z_range[1], SPACING)
    Y, Z = np.meshgrid(ys, zs, indexing="ij")
    return away_from_faces(np.column_stack([np.full(Y.size, x), Y.ravel(), Z.ravel()]), RES)


# rays to the wall cross |y| < 3, |z| < 1 at CAR_X: all around a car there (they stop
# max(0.5 m, 15 %) before the wall, well behind CAR_X)
WALL = plane_x(WALL_X, (-6.0, 6.0), (-2.0, 2.0))


def car_at(y):
    return plane_x(CAR_X, (y - 0.5, y + 0.5), (-0.5, 0.5))


def scene(car_y=None):
    """(points, labels) seen from the origin: the wall, and the car in front of it at car_y
    (the wall behind the car is hidden)."""
    if car_y is None:
        return WALL, np.full(len(WALL), BUILDING)
    s = CAR_X / WALL_X
    hidden = (np.abs(WALL[:, 1] * s - car_y) < 0.5) & (np.abs(WALL[:, 2] * s) < 0.5)
    car = car_at(car_y)
    return (
        np.vstack([WALL[~hidden], car]),
        np.r_[np.full(int((~hidden).sum()), BUILDING), np.full(len(car), CAR)],
    )


def integrate(mapper, k, car_y=None):
    pts, labels = scene(car_y)
    return mapper.integrate(scan_from_world(pts, pose(), DT * k, labels=labels, index=k))


def free_config(**kw):
    """Free space with a ray to every hit voxel (so every car voxel is crossed every scan)."""
    return small_config(free_space=True, free_ray_stride=1, **kw)


def occupancy_after_hits(hit_scans, cfg):
    """A voxel's occupancy evidence after `hit_scans` scans in a row hit it: +1 after each
    scan's decay, clamped."""
    alpha = math.exp(-DT / cfg.tau_s)
    occ = 0.0
    for _ in range(hit_scans):
        occ = min(alpha * occ + 1.0, cfg.occupancy_cap)
    return occ


def after_loss(occ, dt, cfg):
    """A voxel's occupancy evidence after a scan's rays cross it, dt after its last change:
    decayed, -1, clamped."""
    return max(occ * math.exp(-dt / cfg.tau_s) - 1.0, -cfg.occupancy_cap)


def scans_to_clear(hit_scans, cfg):
    """Scans of rays (one per scan after the object left) until a voxel hit `hit_scans`
    times in a row is empty, by the closed form of its occupancy evidence."""
    occ = occupancy_after_hits(hit_scans, cfg)
    n = 0
    while occ > -cfg.empty_evidence:
        occ = after_loss(occ, DT, cfg)
        n += 1
    return n


def car_labels(mapper, y=0.0):
    labels, _ = mapper.query(car_at(y))
    return np.bincount(labels, minlength=C)


@pytest.mark.parametrize("hit_scans", [3, 40])  # moved away soon; parked, then gone
def test_a_car_that_leaves_clears_after_the_predicted_scans(taichi_cpu, hit_scans):
    cfg = free_config()
    mapper = Mapper(cfg)
    for k in range(hit_scans):
        integrate(mapper, k, car_y=0.0)
    assert car_labels(mapper)[CAR] == len(car_at(0.0))
    n = scans_to_clear(hit_scans, cfg)
    assert n <= cfg.occupancy_cap + cfg.empty_evidence + 1  # bounded, however long it stood
    for j in range(n):
        report = integrate(mapper, hit_scans + j)
        assert report.freed_voxels > 0
        labels = car_labels(mapper)
        if j < n - 1:
            assert labels[CAR] == len(car_at(0.0)), f"cleared {n - 1 - j} scans early"
    assert labels[0] == len(car_at(0.0)), "not cleared when the evidence says so"
    snap = mapper.snapshot()
    gone = snap.dynamic_layer()
    assert len(gone) > 0 and set(gone.labels()) == {CAR}
    assert not np.isin(snap.static_map().labels(), [CAR]).any()


def test_a_wall_behind_a_passing_car_is_kept(taichi_cpu):
    mapper = Mapper(free_config())
    ys = np.linspace(-2.0, 2.0, 25)
    for k, y in enumerate(ys):
        integrate(mapper, k, car_y=float(y))
    for k in range(len(ys), len(ys) + 8):
        integrate(mapper, k)
    labels, _ = mapper.query(WALL)
    assert (labels == BUILDING).all()  # every wall voxel, never seen through
    snap = mapper.snapshot()
    assert not snap.empty()[snap.labels() == BUILDING].any()
    trail = snap.dynamic_layer()
    assert len(trail) and (trail.labels() == CAR).all()
    assert not (snap.static_map().labels() == CAR).any()  # no ghost trail left


def test_points_in_space_seen_empty_are_dynamic(taichi_cpu):
    cfg = free_config()
    mapper = Mapper(cfg)
    for k in range(3):
        integrate(mapper, k, car_y=0.0)
    k = 3
    for _ in range(scans_to_clear(3, cfg)):
        integrate(mapper, k)
        k += 1
    report = integrate(mapper, k, car_y=0.0)  # something comes back where it was empty
    pts, labels = scene(0.0)
    assert report.dynamic.shape == (len(pts),)
    assert report.dynamic[labels == CAR].all()
    assert not report.dynamic[labels == BUILDING].any()
    assert report.dynamic_points == int((labels == CAR).sum())


def test_input_motion_labels_flag_points_and_add_no_evidence(taichi_cpu):
    mapper = Mapper(free_config())
    pts, labels = scene(0.0)
    moving = labels == CAR
    scan = scan_from_world(pts, pose(), 0.0, labels=labels)
    scan.moving = moving
    report = mapper.integrate(scan)
    assert (report.dynamic == moving).all()
    assert car_labels(mapper)[CAR] == 0


def test_without_rays_through_the_map_free_space_changes_nothing(taichi_cpu):
    """The wall alone, seen from the front: the rays stop before it and cross no voxel, so the
    map with free space is the map without it (to float32 rounding: the two layouts compile to
    two kernels, whose fast-math sums may round differently)."""
    snaps = []
    for on in (False, True):
        fresh_runtime()
        mapper = Mapper(small_config(free_space=on))
        for k in range(4):
            report = integrate(mapper, k)
            assert report.freed_voxels == 0
        snaps.append(mapper.snapshot())
    off, on = snaps
    assert off.occupancy is None and on.occupancy is not None
    for name in ("keys", "t_last"):
        assert np.array_equal(getattr(off, name), getattr(on, name)), name
    for name in ("counts", "ell_m"):
        np.testing.assert_allclose(getattr(on, name), getattr(off, name), rtol=1e-5, atol=1e-5)
    assert np.allclose(on.occupancy, occupancy_after_hits(4, small_config()))  # hit every scan


def test_occupancy_travels_through_the_store_and_a_restore(taichi_cpu):
    cfg = free_config()
    mapper = Mapper(cfg)
    for k in range(3):
        integrate(mapper, k, car_y=0.0)
    for k in range(3, 3 + scans_to_clear(3, cfg)):
        integrate(mapper, k)
    before = mapper.snapshot()
    assert before.empty().any()
    # drive away (the window leaves the car and the wall behind), then come back
    far = pose(x=-80.0)
    mapper.integrate(
        scan_from_world(np.array([[-75.1, 0.1, 0.1]]), far, 10.0, labels=np.array([BUILDING]))
    )
    assert mapper.stored_voxels >= len(before)
    labels, _ = mapper.query(car_at(0.0))
    assert (labels == 0).all()  # empty, from the store too
    mapper.integrate(
        scan_from_world(np.array([[4.1, 2.9, 0.1]]), pose(), 10.1, labels=np.array([BUILDING]))
    )
    after = mapper.snapshot()
    keep = np.isin(after.keys.view("i8,i8,i8"), before.keys.view("i8,i8,i8")).ravel()
    assert np.array_equal(after.subset(keep).empty(), before.empty())
    state = mapper.state()
    fresh_runtime()
    restored = Mapper(cfg)
    restored.restore(after, state)
    again = restored.snapshot()
    assert np.array_equal(again.occupancy, after.occupancy)
    assert (restored.query(car_at(0.0))[0] == 0).all()


def test_movable_classes_fade_with_their_own_tau(taichi_cpu):
    """A voxel seen as car (many points), then as building (few), 2 s later: with one tau the
    car's evidence still wins; with a short tau for movable classes the building does."""
    winners = []
    for tau_movable in (None, 0.2):
        fresh_runtime()
        mapper = Mapper(small_config(tau_movable_s=tau_movable))
        voxel = away_from_faces(np.array([[5.1, 0.1, 0.1]]), RES)
        many = np.repeat(voxel, 20, axis=0)
        mapper.integrate(scan_from_world(many, pose(), 0.0, labels=np.full(20, CAR)))
        mapper.integrate(
            scan_from_world(many[:4], pose(), 2.0, labels=np.full(4, BUILDING), index=1)
        )
        winners.append(int(mapper.query(voxel)[0][0]))
    assert winners == [CAR, BUILDING]


def wall_then(mapper, k, t, extra=None, extra_label=CAR):
    """Scan k at time t: the tall wall (whole: its voxels are live), plus `extra` points."""
    pts, labels = WALL, np.full(len(WALL), BUILDING)
    if extra is not None:
        pts = np.vstack([pts, extra])
        labels = np.r_[labels, np.full(len(extra), extra_label)]
    report = mapper.integrate(scan_from_world(pts, pose(), t, labels=labels, index=k))
    return report, labels


def test_an_object_entering_space_seen_empty_is_flagged_at_once(taichi_cpu):
    """Rays to a wall cross the space in front of it, where the map holds no voxel; a car that
    appears there is dynamic in its first scan and leaves nothing in the map. Without the
    memory of space seen empty (seen_empty_s = 0) nothing flags it."""
    flagged = []
    for memory in (4.0, 0.0):
        fresh_runtime()
        mapper = Mapper(free_config(seen_empty_s=memory))
        for k in range(2):
            wall_then(mapper, k, DT * k)
        report, labels = wall_then(mapper, 2, 2 * DT, car_at(0.0))
        assert not report.dynamic[labels == BUILDING].any()
        flagged.append(float(report.dynamic[labels == CAR].mean()))
        if memory:
            assert report.seen_empty_blocks > 0
            assert car_labels(mapper)[CAR] == 0  # no evidence, no voxel
    assert flagged == [1.0, 0.0]


def test_a_car_partly_in_space_seen_empty_is_flagged_whole_with_dynamic_clusters(taichi_cpu):
    """A 5 m car whose near end stands where the wall's rays crossed (|y| < 3 at CAR_X) and
    whose far end stands where no ray has been: free space flags the near end alone, and
    dynamic_clusters spreads that to the whole car, and to nothing of the wall."""
    car = plane_x(CAR_X, (0.0, 5.0), (-0.5, 0.5))
    flagged = []
    for clusters in (False, True):
        fresh_runtime()
        mapper = Mapper(free_config(dynamic_clusters=clusters))
        for k in range(2):
            wall_then(mapper, k, DT * k)
        report, labels = wall_then(mapper, 2, 2 * DT, car)
        assert not report.dynamic[labels == BUILDING].any()
        flagged.append(float(report.dynamic[labels == CAR].mean()))
    assert 0.2 < flagged[0] < 0.8  # the near end only
    assert flagged[1] == 1.0


def test_the_memory_of_space_seen_empty_lasts_seen_empty_s(taichi_cpu):
    cfg = free_config(seen_empty_s=1.0)
    mapper = Mapper(cfg)
    for k in range(2):
        report, _ = wall_then(mapper, k, DT * k)
    held = report.seen_empty_blocks
    car = car_at(0.0)
    labels = np.full(len(car), CAR)
    # the last rays through the car's place were at DT: it is dynamic until DT + 1 s ...
    early = mapper.integrate(scan_from_world(car, pose(), DT + 0.95, labels=labels, index=2))
    assert early.dynamic.all()
    # ... and static after; the memory, pruned every quarter of its span, then holds only
    # what the rays to the car crossed
    late = mapper.integrate(scan_from_world(car, pose(), DT + 1.3, labels=labels, index=3))
    assert not late.dynamic.any()
    assert 0 < late.seen_empty_blocks < held / 2
    assert car_labels(mapper)[CAR] == len(car)


def test_a_jump_as_far_as_the_storage_wraps_forgets_the_memory(taichi_cpu):
    """The memory is stored modulo the storage extent: after a jump of exactly that much, a
    place never seen shares the cells of the space seen empty, and must not be flagged."""
    mapper = Mapper(free_config())
    for k in range(2):
        wall_then(mapper, k, DT * k)
    wrap_m = mapper.geometry.storage_extent[0] * RES
    car = car_at(0.0) + np.array([wrap_m, 0.0, 0.0])
    report = mapper.integrate(
        scan_from_world(car, pose(x=wrap_m), 2 * DT, labels=np.full(len(car), CAR), index=2)
    )
    assert not report.dynamic.any()


def test_a_pole_the_rays_pass_beside_is_kept(taichi_cpu):
    """A pole thinner than a voxel, seen whole once and then a third of its voxels per scan,
    with rays to a wall passing through the rest of its voxels: a voxel next to one the scan
    hits keeps its evidence. (Without that rule each voxel gains one scan in three and loses
    two, and the pole is gone within a dozen scans.)"""
    rows = np.arange(-5, 5)
    pole = away_from_faces(np.column_stack([np.full(10, 5.02), np.full(10, 0.02), rows * RES]), RES)
    mapper = Mapper(free_config())
    for k in range(15):
        part = pole if k == 0 else pole[rows % 3 == k % 3]
        wall_then(mapper, k, DT * k, part, POLE)
    labels, _ = mapper.query(pole)
    assert (labels == POLE).all()


def pole_hit_three_scans(cfg, label=POLE):
    """(map, pole points): a fresh map whose first three scans hit the wall and a pole 5 m in
    front of it (points of `label`), one a voxel layer, within the rays to the wall."""
    fresh_runtime()
    rows = np.arange(-4, 4)
    pole = away_from_faces(np.column_stack([np.full(8, 5.02), np.full(8, 0.02), rows * RES]), RES)
    mapper = Mapper(cfg)
    for k in range(3):
        wall_then(mapper, k, DT * k, pole, label)
    return mapper, pole


@pytest.mark.parametrize(("label", "spare"), [(POLE, True), (POLE, False), (CAR, True)])
def test_a_pole_no_scan_hits_for_a_while_is_kept(taichi_cpu, label, spare):
    """A pole hit by three scans, then by none for ten (the rings miss a thin pole) while rays
    to the wall pass through its voxels, with nothing around them hit: with spare_thin_static
    (and neither a hold nor a limit on the crossings) its voxels keep their evidence, as a
    pole cannot have gone. Without the rule it clears after the scans the closed form gives,
    and so does a car in its place with the rule (a movable class)."""
    cfg = free_config(spare_thin_static=spare, thin_static_hold_s=None, thin_static_crossings=None)
    mapper, pole = pole_hit_three_scans(cfg, label)
    assert (mapper.query(pole)[0] == label).all()
    assert scans_to_clear(3, cfg) < 10
    for k in range(3, 13):
        wall_then(mapper, k, DT * k)
    kept = mapper.query(pole)[0] == label
    if label == POLE and spare:
        assert kept.all()
    else:
        assert not kept.any()


def scan_cleared(cfg, losing):
    """The scan (3-29) in which a voxel hit by scans 0-2 is empty by the closed form, when the
    scans k for which losing(k) is true each take one evidence after the decay since the last
    change (None: not by scan 29)."""
    occ, t_last = occupancy_after_hits(3, cfg), DT * 2
    for k in range(3, 30):
        if losing(k):
            occ, t_last = after_loss(occ, DT * k - t_last, cfg), DT * k
        if occ <= -cfg.empty_evidence:
            return k
    return None


def wall_alone_until(mapper, pole, cleared_at, last=20):
    """Scans of the wall alone from scan 3 on: the pole is kept in each until `cleared_at`,
    gone in that one (None: kept up to scan `last`)."""
    for k in range(3, cleared_at + 1 if cleared_at else last):
        wall_then(mapper, k, DT * k)
        kept = mapper.query(pole)[0] == POLE
        assert kept.all() if k != cleared_at else not kept.any(), k


@pytest.mark.parametrize("hold", [0.45, 0.15])
def test_a_pole_hit_only_briefly_keeps_its_spare_for_the_hold(taichi_cpu, hold):
    """thin_static_hold_s: a pole hit by three scans (0.2 s from the first hit to the last),
    then by none while rays to the wall cross its voxels. With a hold longer than that span,
    its voxels keep their evidence through the hold and then clear in the scans the closed
    form gives (decayed from the last hit to the first crossing, then one loss a scan), as what
    a walker labelled trunk or pole leaves does. With a hold shorter than the span, the pole
    has stood long enough: it keeps its evidence for good."""
    # (no multiple of DT: no scan on its end)
    cfg = free_config(thin_static_hold_s=hold, thin_static_crossings=None)
    mapper, pole = pole_hit_three_scans(cfg)
    t_first, t_hit = 0.0, DT * 2
    # the closed form: no change while held, then each scan's crossing after the decay
    cleared_at = scan_cleared(cfg, lambda k: t_hit - t_first < hold and DT * k - t_hit > hold)
    if hold > t_hit - t_first:
        assert cleared_at is not None and cleared_at > 3 + hold / DT
    else:
        assert cleared_at is None
    wall_alone_until(mapper, pole, cleared_at)


@pytest.mark.parametrize("limit", [2, 5])
def test_a_pole_seen_through_scan_after_scan_loses_its_spare(taichi_cpu, limit):
    """thin_static_crossings (no hold): a pole hit by three scans, then by none while rays to
    the wall cross its voxels scan after scan: they keep their evidence for `limit` scans of
    crossings, then clear in the scans the closed form gives (decayed from the last hit to the
    first crossing that counts, then one loss a scan), as what a walker labelled pole leaves."""
    cfg = free_config(thin_static_hold_s=None, thin_static_crossings=limit)
    mapper, pole = pole_hit_three_scans(cfg)
    cleared_at = scan_cleared(cfg, lambda k: k >= 3 + limit)
    assert cleared_at is not None
    wall_alone_until(mapper, pole, cleared_at)


def test_a_pole_hit_now_and_then_keeps_its_spare(taichi_cpu):
    """thin_static_crossings 2 (no hold): a pole the rings hit one scan in three, while in the
    other two rays to the wall cross its voxels, is seen through in no more than two scans
    since a hit: it keeps its evidence for good. With a limit of 0 every crossing counts, two
    losses a hit, and it clears."""
    kept = {}
    for limit in (2, 0):
        cfg = free_config(thin_static_hold_s=None, thin_static_crossings=limit)
        mapper, pole = pole_hit_three_scans(cfg)  # (scans 0, 1, 2: then one in three)
        for k in range(3, 30):
            wall_then(mapper, k, DT * k, pole if k % 3 == 0 else None, POLE)
        kept[limit] = mapper.query(pole)[0] == POLE
    assert kept[2].all()
    assert not kept[0].any()


def box_seen_from_the_front(with_roof):
    """(points, labels): a car-sized box whose front face is at CAR_X and whose roof, below the
    sensor, reaches 2 m back, and the wall behind it minus what the box hides. `with_roof`:
    the roof's points too (a scan whose rings miss the roof has the rest only)."""
    top, back, half_y = -0.39, CAR_X + 2.0, 1.0  # (a roof low in its voxel layer)
    front = plane_x(CAR_X, (-half_y, half_y), (-2.0, top))
    xs = np.arange(CAR_X + SPACING / 2, back, SPACING)
    ys = np.arange(-half_y + SPACING / 2, half_y, SPACING)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    roof = away_from_faces(np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, top)]), RES)
    # a wall point is hidden when its ray meets the front face or the roof
    x_top = np.where(WALL[:, 2] < 0, top * WALL_X / np.minimum(WALL[:, 2], -1e-9), np.inf)
    by_front = (np.abs(WALL[:, 1] * CAR_X / WALL_X) < half_y) & (WALL[:, 2] * CAR_X / WALL_X < top)
    by_roof = (x_top >= CAR_X) & (x_top <= back) & (np.abs(WALL[:, 1] * x_top / WALL_X) < half_y)
    wall = WALL[~(by_front | by_roof)]
    parts = [(wall, BUILDING), (front, CAR)] + ([(roof, CAR)] if with_roof else [])
    return (
        np.vstack([p for p, _ in parts]),
        np.concatenate([np.full(len(p), c) for p, c in parts]),
        roof,
    )


@pytest.mark.parametrize("spare", [True, False])
def test_a_roof_the_rays_graze_is_kept(taichi_cpu, spare):
    """A parked car's roof seen from above at a shallow angle, then scans whose rings miss it
    while rays to the wall behind pass just over it, through the roof's voxels: each of those
    voxels borders the inside of the car, which no ray has seen, so it keeps its evidence
    (spare_beside_unseen). Without that rule the rays wear the far end of the roof away."""
    fresh_runtime()
    mapper = Mapper(free_config(spare_beside_unseen=spare))
    for k in range(16):
        pts, labels, roof = box_seen_from_the_front(with_roof=k < 4)
        mapper.integrate(scan_from_world(pts, pose(), DT * k, labels=labels, index=k))
    kept = mapper.query(roof)[0] == CAR
    if spare:
        assert kept.all()
    else:
        assert (~kept).sum() > 0.05 * len(roof)


@pytest.mark.parametrize(("label", "spare"), [(POLE, True), (POLE, False), (CAR, True)])
def test_a_pole_seen_first_in_part_grows_into_space_seen_empty(taichi_cpu, label, spare):
    """A pole whose lower half is seen first while rays to the wall pass through the voxels
    of its upper half (remembered as seen empty), then whole: each scan its points next to
    its live voxels are not flagged (spare_static_beside_own), so it grows a voxel a scan to
    its top. A car in its place is flagged (a movable class gets no such rule: a car that
    drives into space seen empty beside a parked one is dynamic), and so is the pole without
    the rule."""
    fresh_runtime()
    rows = np.arange(-4, 4)  # (z within the rays to the wall: no voxel of it borders unseen space)
    pole = away_from_faces(np.column_stack([np.full(8, 5.02), np.full(8, 0.02), rows * RES]), RES)
    upper = rows >= 0
    mapper = Mapper(free_config(spare_static_beside_own=spare))
    wall_then(mapper, 0, 0.0, pole[~upper], label)
    flagged = []
    for k in range(1, 8):
        report, labels = wall_then(mapper, k, DT * k, pole, label)
        flagged.append(int(report.dynamic[labels == label].sum()))
    live = {tuple(k) for k in mapper.snapshot().keys.tolist()}
    in_map = np.array([tuple(k) in live for k in voxel_keys(pole, RES).tolist()])
    if label == POLE and spare:
        # one row more of the upper half is live each scan: 3, 2, 1 of its 4 rows flagged
        assert flagged == [3, 2, 1, 0, 0, 0, 0]
        assert in_map.all() and (mapper.query(pole)[0] == POLE).all()
    else:
        assert flagged == [4] * 7
        assert in_map[~upper].all() and not in_map[upper].any()
