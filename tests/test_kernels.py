"""Each kernel stage of the engine against numpy.

* the sparse kernel g(r) table, the entropy and the adaptive length against `tisem.reference`;
* rasterisation, filtering, entropy and query on a scan of hand-placed points;
* every stage of `Mapper.integrate` (located voxels, training points, kernel update + fusion,
  query) against `tisem.reference.ReferenceMapper` on random scans, for every mode and
  several seeds (set TISEM_TEST_SEEDS="3,4,5" to try others; a failure names its seed).
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from helpers import (
    C,
    away_from_faces,
    check_scan_orders,
    engine_entropy,
    hand_rasterize,
    kernel_table_fields,
    located_voxels,
    one_hot,
    pose,
    sample_kernel,
    scan_from_world,
    small_config,
    training_points,
    voxel_keys,
)
from scipy.spatial import cKDTree

from tisem.class_centroids import CENTROID_COLS, MIN_SEPARATION, SLOT, two_leading
from tisem.mapper import Mapper
from tisem.reference import ReferenceMapper, normalized_entropy, sparse_kernel
from tisem.scan import Scan
from tisem.trace import IntegrationTrace

# --------------------------------------------------------------------------- g(r), entropy


def test_reference_formulas_by_hand():
    """The oracle itself, on values worked out by hand."""
    # g(r) = (2 + cos 2 pi r)/3 (1 - r) + sin(2 pi r)/(2 pi)
    assert sparse_kernel(0.0) == 1.0
    assert sparse_kernel(0.5) == pytest.approx(1 / 6, abs=1e-15)  # (2 - 1)/3 * 1/2 + 0
    assert sparse_kernel(0.25) == pytest.approx(0.5 + 1 / (2 * math.pi), abs=1e-15)
    assert sparse_kernel(1.0) == 0.0 and sparse_kernel(1.7) == 0.0
    p = np.zeros((3, C))
    p[0, 1:] = 5.0  # uniform over the 19 real classes
    p[1, 9] = 7.0  # one class
    p[2, [3, 4]] = 1.0
    p[:, 0] = 100.0  # class 0 is outside the support
    np.testing.assert_allclose(
        normalized_entropy(p), [1.0, 0.0, math.log(2) / math.log(19)], atol=1e-15
    )


def test_sparse_kernel_table(taichi_cpu):
    fields = kernel_table_fields()
    r2 = np.concatenate([np.linspace(0, 1, 200_001), [0.0, 1.0, 1.0 + 1e-6, 1.5, 4.0]])
    lut, exact = sample_kernel(fields, r2)
    want = sparse_kernel(np.sqrt(r2.astype(np.float32).astype(np.float64)))
    assert lut[-5] == 1.0, "g(0) must be exactly 1"
    assert abs(lut[-4]) < 1e-7 and abs(exact[-4]) < 1e-7, "g(1) must be 0"
    assert np.all(lut >= 0) and np.all(lut[-3:] < 1e-7), "g >= 0, and 0 past r = 1"
    err = np.abs(lut - want)
    assert err.max() < 1e-6, f"table error {err.max():.2e} at r^2 = {r2[err.argmax()]:.6f}"
    assert np.abs(exact - want).max() < 1e-6
    assert np.all(np.diff(lut[:200_001]) <= 1e-7), "g must decrease on [0, 1]"


def test_entropy_and_adaptive_length_match_reference(taichi_cpu):
    rng = np.random.default_rng(7)
    prior, ell_min, ell_max = 2.0, 0.4, 1.2
    rows = [
        np.full(C, 3.0),  # uniform -> H = 1 -> L_max
        np.r_[0.0, np.full(C - 1, 0.01)],  # uniform, tiny
        prior + 1000.0 * one_hot([9])[0],  # one class, lots of evidence
        1000.0 * one_hot([9])[0],  # one class only: H = 0 -> L_min
        np.r_[50.0, np.full(C - 1, 1.0)],
    ]  # class 0 mass is ignored
    for alpha in (0.05, 0.5, 5.0):
        rows += list(prior + rng.gamma(alpha, 3.0, (40, C)) * (rng.random((40, C)) < 0.6))
    p = np.array(rows)
    h, ell, h_prior = engine_entropy(p, ell_min, ell_max, common=prior)
    want = normalized_entropy(p)
    np.testing.assert_allclose(h, want, atol=2e-6)
    # the shortcut the kernel update takes for classes at the prior (most rows have some)
    assert np.count_nonzero(p[:, 1:] == np.float32(prior)) > len(p)
    np.testing.assert_allclose(h_prior, want, atol=2e-6)
    np.testing.assert_allclose(ell, ell_min + (ell_max - ell_min) * want, atol=2e-6)
    assert ell[0] == pytest.approx(ell_max, abs=1e-6) and ell[1] == pytest.approx(ell_max, abs=1e-6)
    assert ell[3] == pytest.approx(ell_min, abs=1e-6)
    assert ell[2] - ell_min < 0.1 * (ell_max - ell_min)  # near L_min despite the prior
    assert ell[4] == pytest.approx(ell_max, abs=1e-6)


# --------------------------------------------------------------------------- known points


def test_rasterize_filter_entropy_query_on_known_points(taichi_cpu):
    """A scan of hand-placed points: what lands in each voxel, what the filter keeps, each
    training voxel's kernel length, and what a query returns where there is no voxel."""
    res = 0.2
    cfg = small_config(mode="adaptive", min_points=3, min_range_m=1.0, prior=2.0)
    mapper = Mapper(cfg)
    trace = IntegrationTrace()
    rng = np.random.default_rng(0)
    T = pose(3.3, -1.1, 1.7)

    def in_voxel(key, n):
        return (np.asarray(key) + rng.uniform(0.05, 0.95, (n, 3))) * res

    groups = {  # voxel key (global) -> (points, labels)
        "A": ((40, -5, 3), np.full(1000, 9)),  # one class, many points
        "B": ((40, 15, 3), np.arange(1, 20)),  # 19 classes, one each
        "D": ((10, 20, 2), np.array([11, 11, 11, 13, 0, 0])),  # mixed, with unlabeled
        "E": ((5, 30, 3), np.array([11, 0, 0])),  # 3 points, 1 labelled
        "F": ((5, -30, 3), np.array([13, 13])),  # 2 points < min_points
        "G": ((-20, -20, 4), np.array([0, 0, 0, 0])),  # no class evidence
    }
    pts, labels = [], []
    for key, lab in groups.values():
        pts.append(in_voxel(key, len(lab)))
        labels.append(lab)
    world = np.concatenate(pts)
    labels = np.concatenate(labels).astype(np.int32)
    sensor = (world - T[:3, 3]) @ T[:3, :3]
    # dropped before rasterisation: out of range (far, too near), above the height band,
    # non-finite
    extra = np.array([[25.0, 0, 0], [0.3, 0.2, 0.1], [3.0, 0, 6.0], [np.nan, 1, 1], [1, np.inf, 1]])
    sensor = np.concatenate([sensor, extra])
    labels = np.concatenate([labels, [9, 9, 9, 9, 9]]).astype(np.int32)
    scan = Scan(points_sensor=sensor, T_world_sensor=T, stamp_s=50.0, labels=labels)

    rep = mapper.integrate(scan, trace=trace)
    assert (
        rep.points,
        rep.used,
        rep.dropped_nonfinite,
        rep.dropped_range,
        rep.dropped_band,
        rep.dropped_window,
    ) == (len(sensor), len(world), 2, 2, 1, 0)

    # located voxels: every hit voxel, with its point count (unlabeled points count) and how
    # many of its points carry evidence (unlabeled points do not)
    layer = located_voxels(trace.scans[0])
    want_keys = np.array(sorted(k for k, _ in groups.values()))
    np.testing.assert_array_equal(layer["keys"], want_keys)
    for key, lab in groups.values():
        i = np.flatnonzero((layer["keys"] == key).all(axis=1))[0]
        assert layer["npts"][i] == len(lab), key
        assert layer["labelled"][i] == np.count_nonzero(lab), key

    # the filter: >= min_points points and some class evidence (E has 3 points, 1 labelled);
    # each kept voxel's training point: the centroid of all its points, the histogram of its
    # labelled ones
    kept = np.array(sorted(groups[g][0] for g in "ABDE"))
    got = training_points(trace.scans[0])
    np.testing.assert_array_equal(got["keys"], kept)
    k_world = voxel_keys(world, res)
    for i, key in enumerate(got["keys"]):
        g = next(g for g in "ABDE" if groups[g][0] == tuple(key))
        lab = groups[g][1]
        np.testing.assert_array_equal(
            got["hist"][i], np.bincount(lab[lab > 0], minlength=C), err_msg=g
        )
        inside = (k_world == key).all(axis=1)
        np.testing.assert_allclose(
            got["centroid"][i], world[inside].mean(axis=0), atol=1e-5, err_msg=g
        )
    snap = mapper.snapshot()
    np.testing.assert_array_equal(snap.keys, kept)  # only training voxels become map voxels

    # the adaptive length from p = prior + decayed map counter (0 here) + h
    hist = np.array(
        [np.bincount(groups[g][1][groups[g][1] > 0], minlength=C) for g in "ABDE"], np.float64
    )
    order = np.lexsort(np.array([groups[g][0] for g in "ABDE"]).T[::-1])
    span = cfg.ell_max_m - cfg.ell_min_m
    want_ell = cfg.ell_min_m + span * normalized_entropy(cfg.prior + hist)
    np.testing.assert_allclose(snap.ell_m, want_ell[order], atol=2e-6)
    got = {g: snap.ell_m[np.flatnonzero((snap.keys == groups[g][0]).all(axis=1))[0]] for g in "AB"}
    assert got["B"] == pytest.approx(cfg.ell_max_m, abs=1e-6)  # uniform -> L_max
    assert got["A"] - cfg.ell_min_m < 0.1 * span, got  # one class -> near L_min

    # query: labels of the kept voxels; 0 and zero probabilities where there is no voxel and
    # none within the query radius: an empty voxel inside the window, the filtered voxels F
    # and G, outside the window, very far, non-finite
    q = np.array(
        [(np.array(groups[g][0]) + 0.5) * res for g in "ADEFG"]
        + [[10.0, 10.0, 0.5], [300.0, 0, 0], [1e9, -1e9, 0], [np.nan, 0, 0]]
    )
    lab, prob = mapper.query(q)
    assert lab[:3].tolist() == [9, 11, 11]
    np.testing.assert_allclose(prob[:3].sum(axis=1), 1.0, atol=1e-6)
    assert lab[3:].tolist() == [0] * 6
    assert not prob[3:].any()


@pytest.mark.parametrize("cutoff", [0.85, 1.0])
def test_kernel_cutoff_drops_exactly_the_pairs_beyond_it(taichi_cpu, cutoff):
    """A voxel of class 9, then one point of class 13 at 0.8 L and one at 0.9 L from its
    centre (fixed L = 0.8 m, plain accumulation): the voxel gains sigma0 g(0.8) from the first,
    and sigma0 g(0.9) from the second only when the cutoff lies beyond 0.9 L."""
    res, ell = 0.2, 0.8
    cfg = small_config(
        mode="bki",
        ell_fixed_vox=ell / res,
        thin_classes=[],
        vehicle_classes=[],
        kernel_cutoff=cutoff,
    )
    mapper = Mapper(cfg)
    T = pose(x=-6.0)
    centre = np.array([0.1, 0.1, 0.1])  # voxel (0, 0, 0)
    mapper.integrate(scan_from_world(centre[None], T, 1.0, labels=np.array([9], np.int32)))
    near_far = centre + np.array([[0.8 * ell, 0.0, 0.0], [0.0, 0.9 * ell, 0.0]])
    scan = scan_from_world(near_far, T, 1.1, labels=np.array([13, 13], np.int32), index=1)
    mapper.integrate(scan)
    snap = mapper.snapshot()
    row = np.flatnonzero((snap.keys == 0).all(axis=1))
    assert len(row) == 1 and len(snap.keys) == 3
    want = cfg.sigma0 * (sparse_kernel(0.8) + (sparse_kernel(0.9) if cutoff > 0.9 else 0.0))
    assert sparse_kernel(0.9) > 50 * 1e-6  # far above the table's error: the test can see it
    assert snap.counts[row[0], 13] == pytest.approx(want, abs=1e-6)
    assert snap.counts[row[0], 9] == pytest.approx(cfg.sigma0, abs=1e-6)


# --------------------------------------------------------------------------- vs reference

# Each mode runs with a different weighting / filter so that every branch meets the oracle.
MODE_CONFIGS = {
    "csm": dict(point_weight="unit"),
    "bki": dict(point_weight="count", min_points=2, ell_fixed_vox=4.0),
    # (the one mode mapped without evidence caps, query blend and kernel cutoff: the other path
    # of each)
    "adaptive": dict(
        point_weight="unit",
        thin_classes=[],
        vehicle_classes=[],
        query_blend="off",
        kernel_cutoff=1.0,
    ),
    "spatial": dict(point_weight="count"),
    "st": dict(point_weight="count", min_points=2, tau_s=0.5),
}
SEEDS = [int(s) for s in os.environ.get("TISEM_TEST_SEEDS", "11,12,13").split(",")]
SCANS_PER_SEED = 2
POINTS_PER_SCAN = 2500
REGION_STEP_M = 100.0  # seeds alternate between two regions farther apart than the window

# Tolerances (float32 Taichi vs float64 numpy):
CENTROID_ATOL_M = 1e-4  # float32 sums of up to ~100 coordinates of ~20 m
EVIDENCE_RTOL = 1e-5
COUNT_RTOL, COUNT_ATOL = 1e-4, 1e-4  # the table g(r) is within 1e-6 sigma0 of the formula,
# summed over up to ~100 weighted training points
ELL_ATOL_M = 1e-5  # float32 entropy with a polynomial log
T_LAST_ATOL_S = 1e-5  # float32 seconds since the first scan
MIN_T_LAST_MATCH = 0.995
BLEND_ATOL = 1e-3  # a blend of normalised posteriors, each within COUNT_ATOL / total
MIN_BLEND_WEIGHT = 1e-3  # of g over the voxels within the query radius


def random_scans(seed: int, region_x: float, t_start: float, probs: bool):
    """Labelled points on randomly oriented surface patches (one class each, 1-10 points per
    voxel, several classes where patches meet), with label noise including 0, seen from random
    poses, some points out of range or non-finite, at irregular times."""
    rng = np.random.default_rng(seed)
    n_patch = 10
    centres = np.array([region_x, 0.0, 0.0]) + rng.uniform(
        [-9, -9, -2.5], [9, 9, 2.0], (n_patch, 3)
    )
    axes = np.column_stack([rng.uniform(0.3, 0.9, (n_patch, 2)), np.full(n_patch, 0.03)])
    rot = np.array(
        [
            pose(yaw=a, pitch=b, roll=c)[:3, :3]
            for a, b, c in rng.uniform(-math.pi, math.pi, (n_patch, 3))
        ]
    )
    cls = rng.integers(1, C, n_patch)
    scans, t = [], t_start
    for i in range(SCANS_PER_SEED):
        T = pose(
            region_x + rng.uniform(-1.5, 1.5),
            rng.uniform(-1.5, 1.5),
            1.5 + rng.uniform(-0.2, 0.2),
            yaw=rng.uniform(-math.pi, math.pi),
            pitch=rng.uniform(-0.05, 0.05),
            roll=rng.uniform(-0.05, 0.05),
        )
        k = rng.integers(0, n_patch, POINTS_PER_SCAN)
        local = rng.normal(0, 1, (POINTS_PER_SCAN, 3)) * axes[k]
        world = centres[k] + np.einsum("nij,nj->ni", rot[k], local)
        world = away_from_faces(world, 0.2)
        lab = cls[k].astype(np.int32)
        noisy = rng.random(POINTS_PER_SCAN) < 0.25
        lab[noisy] = rng.integers(0, C, noisy.sum())
        t += rng.uniform(0.05, 0.4)
        if probs:
            p = 0.5 * one_hot(lab) + 0.5 * rng.dirichlet(np.full(C, 0.2), POINTS_PER_SCAN)
            p[rng.random(POINTS_PER_SCAN) < 0.05] = 0.0  # no evidence at all
            scan = scan_from_world(world, T, t, probs=p.astype(np.float32), index=i)
        else:
            scan = scan_from_world(world, T, t, labels=lab, index=i)
        bad = rng.choice(POINTS_PER_SCAN, 6, replace=False)
        scan.points_sensor[bad[:2], 0] = np.nan
        scan.points_sensor[bad[2], 1] = np.inf
        scan.points_sensor[bad[3]] = [30.0, 0, 0]  # beyond max_range
        scan.points_sensor[bad[4]] = [0.5, 0.5, 0]  # within min_range
        scan.points_sensor[bad[5]] = [5.0, 0, -6.0]  # below the height band
        scans.append(scan)
    return scans, t


def _check_stages(step, scan, ref, cfg, where):
    """Steps 1-3 of a traced scan: the located voxels by hand, the training points by the
    reference."""
    keys, npts, _, hist = hand_rasterize(scan, cfg)
    check_scan_orders(step, where)
    layer = located_voxels(step)
    np.testing.assert_array_equal(layer["keys"], keys, err_msg=f"{where}: located voxels")
    np.testing.assert_array_equal(layer["npts"], npts, err_msg=f"{where}: points per voxel")
    # (a voxel with evidence has a labelled point, or a point with a positive probability)
    np.testing.assert_array_equal(
        layer["labelled"] > 0, hist.sum(axis=1) > 0, err_msg=f"{where}: voxels with class evidence"
    )
    r_keys, r_centroid, r_h, _ = ref.rasterize(scan)
    r_keys = r_keys + ref.origin_vox
    order = np.lexsort(r_keys.T[::-1])
    got = training_points(step)
    np.testing.assert_array_equal(got["keys"], r_keys[order], err_msg=f"{where}: training voxels")
    np.testing.assert_allclose(
        got["centroid"],
        r_centroid[order] + ref.origin_vox * ref.res,
        rtol=0,
        atol=CENTROID_ATOL_M,
        err_msg=f"{where}: training points",
    )
    np.testing.assert_allclose(
        got["hist"],
        r_h[order],
        rtol=EVIDENCE_RTOL,
        atol=1e-6,
        err_msg=f"{where}: training evidence",
    )


def _check_map(mapper, ref, tainted: set, where: str, query_pts):
    """Steps 4-9: voxels, counters, t_last, kernel lengths, labels and query answers.

    Tolerated (and documented): a voxel whose nearest training point sits at its kernel's
    edge (d within float error of L(v), where g ~ 0) or whose whole update is within float
    error of the 1e-6 noise threshold (`kernels.bki.MIN_UPDATE`) can be updated by one
    implementation and not the other (float32 vs float64). The evidence involved is ~1e-6,
    but the update also stamps t_last, and with decay (st, spatial) that rescales all of the
    voxel's counters at its next update. Such voxels are marked `tainted` for the rest of the
    run; they must stay under 0.5 %, and everything else must agree to float tolerance.
    """
    snap = mapper.snapshot()
    keys, counts, t_last, ell = ref.voxels()
    assert len(snap) == len(keys), f"{where}: {len(snap)} voxels in tisem, {len(keys)} in numpy"
    np.testing.assert_array_equal(snap.keys, keys, err_msg=f"{where}: voxel keys")
    packed = [tuple(k) for k in keys]
    t_ok = np.abs(snap.t_last - t_last) <= T_LAST_ATOL_S
    tainted.update(k for k, ok in zip(packed, t_ok) if not ok)
    good = np.array([k not in tainted for k in packed])
    assert good.mean() >= MIN_T_LAST_MATCH, (
        f"{where}: only {good.mean():.2%} of voxels agree on t_last (>= 99.5 % required)"
    )
    np.testing.assert_allclose(
        snap.counts[good],
        counts[good],
        rtol=COUNT_RTOL,
        atol=COUNT_ATOL,
        err_msg=f"{where}: counters",
    )
    np.testing.assert_allclose(
        snap.ell_m[good], ell[good], rtol=0, atol=ELL_ATOL_M, err_msg=f"{where}: kernel lengths"
    )
    # labels: equal, except where the reference's two best classes tie within tolerance
    top = np.sort(counts, axis=1)[:, ::-1]
    clear = good & (top[:, 0] - top[:, 1] > COUNT_RTOL * top[:, 0] + 2 * COUNT_ATOL)
    want = np.where(counts.sum(axis=1) > 0, counts.argmax(axis=1), 0)
    got = snap.labels()
    bad = np.flatnonzero(clear & (got != want))
    assert bad.size == 0, (
        f"{where}: labels differ at {keys[bad[:5]].tolist()}: {got[bad[:5]]} vs {want[bad[:5]]}"
    )
    tie = good & ~clear
    assert np.all(counts[tie, got[tie]] >= top[tie, 0] - COUNT_RTOL * top[tie, 0] - 2 * COUNT_ATOL)
    if snap.centroids is not None:
        _check_centroids(snap.centroids[good], ref.voxel_centroids()[good], where)
    lab, _ = mapper.query(snap.centers(), with_probs=False)  # the query sees every voxel
    same = np.ones(len(snap), bool)
    if snap.centroids is not None:  # (kernel and host round the rule's inputs apart)
        half = np.full((len(snap), 3), 0.5 * ref.res)
        same = split_is_clear(snap.counts, snap.centroids, half, ref.config)
    np.testing.assert_array_equal(
        lab[same],
        snap.point_labels(snap.centers())[same],
        err_msg=f"{where}: query vs snapshot",
    )
    if query_pts is None:
        return good.mean()
    # query: the scan points and random points (many in no voxel)
    lab, prob = mapper.query(query_pts)
    r_lab, r_prob = ref.query(query_pts)
    qk = voxel_keys(query_pts, ref.res)
    index = {k: i for i, k in enumerate(packed)}
    vi = np.array([index.get(tuple(k), -1) for k in qk])
    _check_blend(mapper, ref, query_pts, lab, prob, vi < 0, tainted, where)
    sure = (vi >= 0) & clear[np.maximum(vi, 0)]
    if snap.centroids is not None:  # (and the nearer-centroid rule not on a knife's edge)
        row = np.maximum(vi, 0)
        offsets = query_pts - keys[row] * ref.res
        sure &= split_is_clear(counts[row], ref.voxel_centroids()[row], offsets, ref.config)
    np.testing.assert_array_equal(lab[sure], r_lab[sure], err_msg=f"{where}: query labels")
    ok = (vi >= 0) & good[np.maximum(vi, 0)]
    # counters agree to COUNT_ATOL, so c / total to about that over the voxel's total (a voxel
    # reached only by the kernel's edge holds little evidence: loose probabilities)
    total = counts.sum(axis=1)[vi[ok]]
    err = np.abs(prob[ok] - r_prob[ok]).max(axis=1)
    tol = 1e-5 + 3 * COUNT_ATOL / total
    bad = np.flatnonzero(err > tol)
    assert bad.size == 0, (
        f"{where}: query probabilities differ by {err[bad[:3]]} at voxels "
        f"with total evidence {total[bad[:3]]}"
    )
    return good.mean()


def _check_centroids(got: np.ndarray, want: np.ndarray, where: str) -> None:
    """The class centroid slots of the voxels both maps agree on: the same classes, weights
    to the counters' tolerance, mean offsets to the training points' (float32 sums)."""
    np.testing.assert_array_equal(
        got[:, [0, SLOT]], want[:, [0, SLOT]], err_msg=f"{where}: centroid classes"
    )
    weights = [1, SLOT + 1]
    np.testing.assert_allclose(
        got[:, weights],
        want[:, weights],
        rtol=COUNT_RTOL,
        atol=COUNT_ATOL,
        err_msg=f"{where}: centroid weights",
    )
    means = [a for a in range(CENTROID_COLS) if a % SLOT >= 2]
    np.testing.assert_allclose(
        got[:, means],
        want[:, means],
        rtol=0,
        atol=CENTROID_ATOL_M,
        err_msg=f"{where}: centroid means",
    )


def split_is_clear(counts, centroids, offsets, cfg) -> np.ndarray:
    """(N,) whether the nearer-centroid rule decides each point with a margin above float
    error: its voxel's second class clearly above or below centroid_ratio of the first, and
    the point clearly nearer one of the two centroids."""
    best, second = two_leading(counts)
    rows = np.arange(len(counts))
    gap = counts[rows, second] - cfg.centroid_ratio * counts[rows, best]
    ok = np.abs(gap) > COUNT_RTOL * counts[rows, best] + 2 * COUNT_ATOL
    means = np.stack([centroids[:, 2:SLOT], centroids[:, SLOT + 2 :]], axis=1)
    d = np.square(offsets[:, None, :] - means).sum(axis=2)
    sep = np.square(means[:, 0] - means[:, 1]).sum(axis=1)
    margin = 4 * CENTROID_ATOL_M * cfg.resolution_m
    ok &= np.abs(sep - (MIN_SEPARATION * cfg.resolution_m) ** 2) > margin
    return ok & (np.abs(d[:, 0] - d[:, 1]) > margin)


def _check_blend(mapper, ref, pts, lab, prob, missing, tainted, where):
    """Points in no voxel: the blended posterior of the voxels within the query radius, as
    numpy's, where none is tainted (`_check_map`) and the live window holds all of them (the
    kernel reads live voxels only), or outside the window (the host reads every voxel within
    reach there, live or stored)."""
    res, radius = ref.res, ref.config.query_radius_m
    st = mapper.window.state
    local = np.floor(pts / res).astype(np.int64) - mapper.origin_vox
    off = np.abs(local - st.center_vox)
    outside = np.any(off > st.half_vox, axis=1)
    held = np.all(off <= st.half_vox - math.ceil(radius / res) - 1, axis=1) | outside
    if tainted:
        near = cKDTree((np.array(sorted(tainted)) + 0.5) * res).query(
            pts, distance_upper_bound=radius + res
        )[0]
        held &= ~np.isfinite(near)
    # where the voxels within reach all sit at the radius's edge, the blend's total weight is
    # float error (g ~ 0) and its normalised posterior is not comparable
    held &= missing
    weight = ref.blended_posterior(pts[held]).sum(axis=1)
    held[held] = (weight > MIN_BLEND_WEIGHT) | (weight == 0)
    r_lab, r_prob = ref.query(pts[held])
    got_lab, got_prob = lab[held], prob[held]
    top = np.sort(r_prob, axis=1)[:, ::-1]
    clear = top[:, 0] - top[:, 1] > BLEND_ATOL
    np.testing.assert_array_equal(
        got_lab[clear], r_lab[clear], err_msg=f"{where}: blended query labels"
    )
    np.testing.assert_allclose(
        got_prob, r_prob, rtol=0, atol=BLEND_ATOL, err_msg=f"{where}: blended query probabilities"
    )
    return int(np.count_nonzero(r_lab))


FAST_STAGES = {("st", "per block"), ("csm", "per block")}


@pytest.mark.parametrize(
    "mode,loop",
    [
        # st and csm in the fast subset (the method and its floor); the other modes, and the
        # GPUs' loop form, in the full run
        pytest.param(mode, loop, marks=() if (mode, loop) in FAST_STAGES else pytest.mark.slow)
        for mode, loop in [(m, "per block") for m in MODE_CONFIGS]
        + [("st", "per voxel"), ("bki", "per voxel")]
    ],
)
def test_stages_match_reference(taichi_cpu, mode, loop):
    """All of `integrate` against the numpy oracle, stage by stage, after every scan.

    Seeds alternate between two regions 100 m apart (farther than the window): the live
    window moves away, the first region is compared from the host store, and the third seed
    maps it again with its voxels reloaded (their decay then spans the time away). Odd seeds
    feed probabilities instead of labels. The kernel update's GPU loop form (one thread per
    voxel) is checked here on the CPU too.
    """
    cfg = small_config(mode=mode, **MODE_CONFIGS[mode])
    mapper = Mapper(cfg, parallel_loop="voxel" if loop == "per voxel" else "block")
    ref = ReferenceMapper(small_config(mode=mode, **MODE_CONFIGS[mode]))
    trace = IntegrationTrace()
    tainted: set = set()
    t, done, reloaded, all_scans = 100.0, 0, 0, []
    rng = np.random.default_rng(SEEDS[0])
    for j, seed in enumerate(SEEDS):
        scans, t = random_scans(seed, (j % 2) * REGION_STEP_M, t + 0.5, probs=bool(j % 2))
        for i, scan in enumerate(scans):
            where = f"mode {mode}, seed {seed}, scan {i} ({'probabilities' if j % 2 else 'labels'})"
            rep = mapper.integrate(scan, trace=trace)
            reloaded += rep.reloaded_voxels
            _check_stages(trace.scans[done], scan, ref, cfg, where)
            ref.integrate(scan)
            done += 1
            all_scans.append(scan)
            q = None
            if i == len(scans) - 1:  # the query (numpy's is slow) once per seed
                pts = np.concatenate([s.points_world() for s in all_scans])
                pts = pts[np.isfinite(pts).all(axis=1)]
                lo, hi = pts.min(axis=0) - 2, pts.max(axis=0) + 2
                q = np.concatenate([pts[::5], rng.uniform(lo, hi, (500, 3))])
            share = _check_map(mapper, ref, tainted, where, q)
    print(f"mode {mode}, seeds {SEEDS}: {share:.4%} of {len(ref.keys)} voxels agree on t_last")
    if len(SEEDS) > 2:
        assert reloaded > 0, "the first region should have come back from the store"
