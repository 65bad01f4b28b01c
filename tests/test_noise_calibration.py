"""The label-noise calibration: measured statistics on a hand-made folder with known answers,
the profile fit, the noise model's fields, and a synthetic street's statistics against the
real network's (targets measured by benchmarks/noise_calibration.py on SemanticKITTI 08
frames 0-4; a slow test re-measures them when the data is present)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from tisem.labels import CLASS_NAMES, NUM_CLASSES
from tisem.synth import SyntheticSequence, calibration, kitti08_counts, profile
from tisem.synth.noise import (
    BOUNDARY_NEIGHBOURS,
    BOUNDARY_RADIUS_M,
    NoiseModel,
    class_boundary,
    drifting_field,
    gaussian_fields,
)

# the real network on frames 0-4 (benchmarks/noise_calibration.py)
REAL = {
    "accuracy": 0.850,
    "coherence_first_bin": 0.678,
    "persistence_lag1": 0.765,
    "persistence_right_lag1": 0.043,
    "moving_car_recall": 0.989,
    "moving_person_recall": 0.0,
}

ROAD, SIDEWALK, CAR, BUILDING, VEGETATION, TERRAIN = 40, 48, 10, 50, 70, 72  # raw ids
TRAIN = {40: 9, 48: 11, 10: 1, 50: 13, 70: 15, 72: 17, 252: 1}


# ----------------------------------------------------------------------------- a tiny folder

# x (m, on a line through the sensor), ground truth, prediction in scans 0 and 1
TINY_POINTS = [
    (3.0, ROAD, ROAD, ROAD),  # right
    (3.3, SIDEWALK, ROAD, ROAD),  # 0.3 m from the road point: a boundary, bleeding
    (7.0, ROAD, SIDEWALK, ROAD),  # isolated error, right in scan 1
    (12.0, CAR, CAR, CAR),
    (25.0, VEGETATION, TERRAIN, TERRAIN),  # wrong in both scans
    (45.0, BUILDING, BUILDING, BUILDING),
    (60.0, BUILDING, ROAD, ROAD),  # beyond 50 m: not evaluated
]
MOVING_CAR_XY = (20.0, 5.0)  # raw 252, predicted car
UNLABELED_XY = (20.0, -5.0)  # raw 0, not evaluated


def write_tiny_folder(root: Path) -> Path:
    """Two identical scans (identity poses and extrinsic) of TINY_POINTS and two more points."""
    for sub in ("velodyne", "labels", "predictions"):
        (root / sub).mkdir(parents=True)
    xyz = [(x, 0.0, 0.0) for x, *_ in TINY_POINTS] + [(*MOVING_CAR_XY, 0.0), (*UNLABELED_XY, 0.0)]
    gt = [g for _, g, _, _ in TINY_POINTS] + [252, 0]
    for scan in (0, 1):
        pred = [p[2 + scan] for p in TINY_POINTS] + [CAR, ROAD]
        cloud = np.column_stack([np.array(xyz), np.zeros(len(xyz))]).astype("<f4")
        cloud.tofile(root / "velodyne" / f"{scan:06d}.bin")
        np.array(gt, dtype="<u4").tofile(root / "labels" / f"{scan:06d}.label")
        np.array(pred, dtype="<u4").tofile(root / "predictions" / f"{scan:06d}.label")
    eye = " ".join(f"{v:.1f}" for v in np.eye(4)[:3].ravel())
    (root / "calib.txt").write_text(f"Tr: {eye}\n")
    (root / "poses.txt").write_text(f"{eye}\n{eye}\n")
    return root


@pytest.fixture(scope="module")
def tiny_stats(tmp_path_factory):
    return calibration.measure(
        calibration.read_folder(write_tiny_folder(tmp_path_factory.mktemp("tiny") / "08"))
    )


def test_confusion_accuracy_and_movers(tiny_stats):
    s = tiny_stats
    assert s.scans == 2 and s.points == 2 * 7  # 60 m and raw 0 are left out
    expected = np.zeros((NUM_CLASSES, NUM_CLASSES), dtype=np.int64)
    for scan in (0, 1):
        for _x, g, *pred in TINY_POINTS[:-1]:
            expected[TRAIN[g], TRAIN[pred[scan]]] += 1
        expected[1, 1] += 1  # the moving car, right
    np.testing.assert_array_equal(s.confusion, expected)
    assert s.metrics()["accuracy"] == pytest.approx(9 / 14)
    np.testing.assert_array_equal(s.raw_predictions[252], np.eye(NUM_CLASSES, dtype=int)[1] * 2)
    assert s.raw_predictions[254].sum() == 0


def test_errors_by_range_and_at_boundaries(tiny_stats):
    s = tiny_stats
    # bins 0-5, 5-10, 10-15, 15-20, 20-30, 30-40, 40-50; the moving car is at 20.6 m
    np.testing.assert_array_equal(s.cell_points.sum(axis=(0, 2)), [4, 2, 2, 0, 4, 0, 2])
    np.testing.assert_array_equal(s.cell_errors.sum(axis=(0, 2)), [2, 1, 0, 0, 2, 0, 0])
    rate = s.error_rate_by_range()
    assert rate[0] == 0.5 and np.isnan(rate[3])
    b = s.boundary()  # the road and sidewalk points 0.3 m apart
    assert b["share"] == pytest.approx(4 / 14)
    assert b["error_at_boundary"] == pytest.approx(0.5) and b["bleed"] == 1.0
    assert b["error_inside"] == pytest.approx(3 / 10)


def test_clusters_persistence_and_votes(tiny_stats):
    s = tiny_stats
    # every wrong point is alone within 0.5 m: clusters of one point, no extent
    np.testing.assert_array_equal(s.cluster_points_by_size, [5, 0, 0, 0, 0])
    np.testing.assert_array_equal(s.cluster_points_by_extent, [5, 0, 0, 0, 0, 0])
    # scan 1 against scan 0: 3 locations wrong before (2 still, the same way), 4 right (0 now)
    np.testing.assert_array_equal(s.persistence[0], [3, 2, 2, 4, 0])
    assert s.persistence[1:].sum() == 0
    # votes within 0.2 m see only the location itself: scan 0 as labelled; in scan 1 the
    # 7 m point's tie (sidewalk, road) goes to the lower class id, road: right either way
    labelled, voted = s.vote_accuracy()
    assert labelled == pytest.approx(9 / 14) and voted[0] == pytest.approx(9 / 14)


def test_measurements_merge_by_adding_counts(tiny_stats, tmp_path):
    again = calibration.measure(calibration.read_folder(write_tiny_folder(tmp_path / "08")))
    merged = again.merge(tiny_stats)
    assert merged.scans == 4 and merged.points == 2 * tiny_stats.points
    np.testing.assert_array_equal(merged.persistence, 2 * tiny_stats.persistence)
    np.testing.assert_array_equal(merged.raw_predictions[252], 2 * tiny_stats.raw_predictions[252])
    assert merged.metrics()["accuracy"] == tiny_stats.metrics()["accuracy"]


def test_coherence_pairs_match_brute_force(tiny_stats):
    """Every evaluated point is a centre (the samples exceed the scan): count the pairs."""
    xyz = np.array(
        [[x, 0, 0] for x, *_ in TINY_POINTS[:-1]] + [[*MOVING_CAR_XY, 0]], dtype=np.float32
    ).astype(np.float64)
    gt = np.array([TRAIN[p[1]] for p in TINY_POINTS[:-1]] + [1])
    d = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    bins = np.searchsorted(calibration.DISTANCE_EDGES_M, d, side="left") - 1  # (a, b] bins
    expected = np.zeros_like(tiny_stats.pairs)
    for scan in (0, 1):
        pred = np.array([TRAIN[p[2 + scan]] for p in TINY_POINTS[:-1]] + [1])
        wrong = pred != gt
        for i, j in zip(*np.nonzero(~np.eye(len(xyz), dtype=bool))):
            k = bins[i, j]
            if k >= expected.shape[1]:
                continue
            if wrong[i]:
                expected[:3, k] += [1, wrong[j], wrong[j] and pred[j] == pred[i]]
            else:
                expected[3:, k] += [1, wrong[j]]
    np.testing.assert_array_equal(tiny_stats.pairs, expected)
    coh = tiny_stats.coherence()
    assert coh["wrong_given_wrong"][1] == 0.0  # the bleeding point's neighbour is right


# ----------------------------------------------------------------------------- the profile


def test_logistic_fit_recovers_an_additive_model():
    """Cells drawn from a known model with many points: the ridge is negligible."""
    C, B = NUM_CLASSES, len(calibration.RANGE_EDGES_M) - 1
    rng = np.random.default_rng(3)
    beta, alpha, gamma = rng.normal(-2, 0.5, B), rng.normal(0, 1, C), 1.2
    logit = beta[None, :, None] + alpha[:, None, None] + gamma * np.array([0.0, 1.0])
    n = np.full((C, B, 2), 10**7)
    w = np.round(n / (1 + np.exp(-logit))).astype(np.int64)
    table, boundary = profile.fit_error_logits(n, w)
    np.testing.assert_allclose(table, beta[None, :] + alpha[:, None], atol=2e-3)
    np.testing.assert_allclose(boundary, gamma, atol=2e-3)


def test_fit_smooths_where_points_are_few():
    n = np.zeros((NUM_CLASSES, 7, 2), dtype=np.int64)
    w = np.zeros_like(n)
    n[9, :, 0], w[9, :, 0] = 100_000, 10_000  # road: 10 % everywhere
    n[10, 2, 0], w[10, 2, 0] = 3, 3  # parking: 3 points, all wrong
    table, _ = profile.fit_error_logits(n, w)
    p = 1 / (1 + np.exp(-table))
    np.testing.assert_allclose(p[9], 0.1, atol=1e-3)
    assert 0.1 < p[10, 2] < 0.6  # pulled far from 1 by the ridge
    # an unseen class takes the mean class offset: between the two classes seen
    assert np.all((p[9] < p[4]) & (p[4] < p[10]))


def test_wrong_label_rows_and_draws():
    confusion = np.zeros((NUM_CLASSES, NUM_CLASSES))
    confusion[9, 11], confusion[9, 9] = 1000, 5000  # road -> sidewalk, measured
    rows = profile.wrong_label_rows(confusion)
    np.testing.assert_allclose(rows.sum(axis=1), 1.0)
    assert np.all(np.diag(rows) == 0) and np.all(rows[:, 0] == 0)
    assert rows[9, 11] > 0.95  # the measured row dominates its prior
    truck = CLASS_NAMES.index("truck")  # unmeasured: the plausible confusions
    assert rows[truck, CLASS_NAMES.index("car")] == pytest.approx(0.6)
    prof = profile.kitti08_profile()
    u = np.linspace(0, 1, 2000, endpoint=False)
    labels = prof.wrong_label(np.full(len(u), 9), u)
    assert np.all(labels != 9) and np.all(labels > 0)
    share = np.bincount(labels, minlength=NUM_CLASSES) / len(u)
    np.testing.assert_allclose(share, np.diff(prof.wrong_label_cdf[9], prepend=0.0), atol=2e-3)


def test_error_probability_interpolates_in_range():
    prof = profile.kitti08_profile()
    c = prof.range_centres_m
    rows = np.full(4, 9)
    p = prof.error_probability(
        rows, np.array([c[0] - 2, c[2], c[-1] + 30, c[2]]), np.array([False, False, False, True])
    )
    logit = prof.error_logit[9]
    expect = 1 / (
        1 + np.exp(-np.array([logit[0], logit[2], logit[-1], logit[2] + prof.boundary_logit[9]]))
    )
    np.testing.assert_allclose(p, expect)


def test_movers_have_their_own_rows():
    prof = profile.kitti08_profile()
    rows = prof.row_of(np.array([1, 1, 6]), np.array([0, 252, 254]))
    p = prof.error_probability(rows, np.full(3, 20.0), np.ones(3, dtype=bool))
    assert p[1] < 0.05 < p[0] + 0.05 and p[2] > 0.9  # moving cars right, people wrong


@pytest.mark.slow
def test_stored_counts_are_the_real_frames(kitti_mini):
    real = calibration.measure(calibration.read_folder(kitti_mini))
    confusion, points, errors, raw = profile.counts_from_module(kitti08_counts)
    np.testing.assert_array_equal(confusion, real.confusion)
    np.testing.assert_array_equal(points, real.cell_points)
    np.testing.assert_array_equal(errors, real.cell_errors)
    for r, counts in real.raw_predictions.items():
        np.testing.assert_array_equal(raw.get(r, np.zeros(NUM_CLASSES)), counts)
    assert real.metrics()["accuracy"] == pytest.approx(REAL["accuracy"], abs=5e-4)
    assert real.coherence()["wrong_given_wrong"][0] == pytest.approx(
        REAL["coherence_first_bin"], abs=0.01
    )  # sampled centres
    rates = real.persistence_rates()
    assert rates["wrong_given_wrong"][0] == pytest.approx(REAL["persistence_lag1"], abs=5e-4)
    assert rates["wrong_given_right"][0] == pytest.approx(REAL["persistence_right_lag1"], abs=5e-4)


# ----------------------------------------------------------------------------- the fields


def test_gaussian_fields_are_standard_normal_and_smooth():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-200, 200, (40_000, 3))
    a, b = gaussian_fields(pts, 1.0, (11, 12))
    for f in (a, b):
        assert abs(f.mean()) < 0.03 and abs(f.std() - 1) < 0.03
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.03  # keys are independent
    near = gaussian_fields(pts + 0.05, 1.0, (11,))[0]
    far = gaussian_fields(pts + 3.0, 1.0, (11,))[0]
    assert np.corrcoef(a, near)[0, 1] > 0.95 and abs(np.corrcoef(a, far)[0, 1]) < 0.03
    layers = rng.integers(0, 2, len(pts))
    per_class = gaussian_fields(pts, 1.0, (11,), layers)[0]
    assert abs(np.corrcoef(per_class[layers == 1], a[layers == 1])[0, 1]) < 0.05
    np.testing.assert_array_equal(per_class[layers == 0], a[layers == 0])  # layer 0 = none


def test_drifting_field_decorrelates_over_epochs():
    pts = np.random.default_rng(1).uniform(-100, 100, (20_000, 3))
    first = drifting_field(pts, 1.0, 5, 0, 30.0)
    corr = [np.corrcoef(first, drifting_field(pts, 1.0, 5, t, 30.0))[0, 1] for t in (1, 15, 60)]
    assert corr[0] > 0.99 and 0.5 < corr[1] < 0.85 and abs(corr[2]) < 0.05
    assert abs(drifting_field(pts, 1.0, 5, 45, 30.0).std() - 1) < 0.03


def test_class_boundary_matches_brute_force_knn():
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 6, (3000, 3))
    gt = (pts[:, 0] > 3).astype(np.int64) * 4 + (pts[:, 1] > 2) + 9
    dist, idx = cKDTree(pts).query(
        pts, k=BOUNDARY_NEIGHBOURS + 1, distance_upper_bound=BOUNDARY_RADIUS_M
    )
    other = np.where(np.isfinite(dist[:, 1:]), gt[np.minimum(idx[:, 1:], len(gt) - 1)], -1)
    other[other == gt[:, None]] = -1
    expected = other[np.arange(len(gt)), np.argmax(other >= 0, axis=1)]
    np.testing.assert_array_equal(class_boundary(pts, gt), expected)
    assert 0.05 < (expected >= 0).mean() < 0.6


@pytest.mark.slow
def test_error_rate_is_the_profiles_in_expectation():
    """Over many independent fields (seeds), each point is wrong with its probability."""
    seq = SyntheticSequence(2, seed=0, points_per_ring=256)
    f = seq.frame(1)
    gt = np.asarray(calibration.raw_to_train(f.gt_raw)[0], dtype=np.int64)
    world = f.points.astype(np.float64) @ f.T_world_lidar[:3, :3].T + f.T_world_lidar[:3, 3]
    range_m = np.linalg.norm(f.points, axis=1)
    model = NoiseModel()
    mover = np.zeros(len(gt), dtype=np.int64)
    wrong = np.mean(
        [
            model.apply(gt, range_m, world, mover, seed, 1, np.random.default_rng(seed)) != gt
            for seed in range(40)
        ],
        axis=0,
    )
    p = model.profile.error_probability(gt, range_m, class_boundary(world, gt) >= 0)
    # one seed's road is wrong at 4.5 +- 2.6 % (a few coarse patches): 40 seeds, ~3.5 sigma
    assert wrong.mean() == pytest.approx(p.mean(), abs=0.012)
    road = gt == 9
    assert wrong[road].mean() == pytest.approx(p[road].mean(), abs=0.015)


# ----------------------------------------------------------------------------- the street


@pytest.fixture(scope="module")
def street_stats():
    """Six scans of the default street at a quarter of the sensor's columns."""
    return calibration.measure(
        calibration.from_synth_frames(SyntheticSequence(6, seed=0, points_per_ring=256))
    )


@pytest.mark.slow
def test_street_statistics_land_near_the_real_networks(street_stats):
    s = street_stats
    # the class mix differs from the real frames', so accuracy only roughly matches
    assert s.metrics()["accuracy"] == pytest.approx(REAL["accuracy"], abs=0.07)
    coherence = s.coherence()["wrong_given_wrong"]
    assert coherence[0] == pytest.approx(REAL["coherence_first_bin"], abs=0.15)
    assert np.all(np.diff(coherence) < 0)  # falls with distance
    rates = s.persistence_rates()
    assert rates["wrong_given_wrong"][0] == pytest.approx(REAL["persistence_lag1"], abs=0.1)
    assert rates["wrong_given_right"][0] == pytest.approx(REAL["persistence_right_lag1"], abs=0.04)
    b = s.boundary()
    assert b["error_at_boundary"] > 2 * b["error_inside"]
    by_range = s.error_rate_by_range()
    assert by_range[-1] > 1.5 * by_range[1]  # errors grow with range
    assert s.raw_prediction_shares(252)[1] == pytest.approx(REAL["moving_car_recall"], abs=0.05)
    person = s.raw_prediction_shares(30)  # the walking person
    assert person[CLASS_NAMES.index("person")] < 0.2


def test_street_recall_follows_the_profile(street_stats):
    """Per class, the measured recall is the profile's at the street's ranges (roughly:
    errors come in patches, so a few scans hold few independent ones)."""
    recall = np.diag(street_stats.row_normalised())
    for name, lo, hi in (
        ("road", 0.9, 1.0),
        ("car", 0.9, 1.0),
        ("parking", 0.0, 0.6),
        ("person", 0.0, 0.2),
    ):
        assert lo <= recall[CLASS_NAMES.index(name)] <= hi, name


def test_noise_calibration_benchmark_runs(tmp_path, capsys):
    from benchmarks import noise_calibration

    data = write_tiny_folder(tmp_path / "real")
    md = tmp_path / "table.md"
    assert (
        noise_calibration.main(
            [
                "--data",
                str(data),
                "--synthetic-scans",
                "2",
                "--seeds",
                "0",
                "1",
                "--points-per-ring",
                "64",
                "--markdown",
                str(md),
                "--write-counts",
                str(tmp_path / "counts.py"),
                "--json",
                str(tmp_path / "t.json"),
            ]
        )
        == 0
    )
    text = md.read_text()
    for heading in (
        "Per class",
        "Largest confusions",
        "by range",
        "boundaries",
        "coherence",
        "clusters",
        "Persistence",
        "mapper could fix",
        "Moving objects",
    ):
        assert heading in text, heading
    assert "| accuracy of the input | 0.643 |" in capsys.readouterr().out
    assert "CONFUSION" in (tmp_path / "counts.py").read_text()
