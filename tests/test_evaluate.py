"""tisem.evaluate: a hand-computed example, a numpy-only reference, tables, and the real data."""

from __future__ import annotations

import numpy as np
import pytest

from tisem.evaluate import Confusion, format_per_class, format_table, network_labels, score_scan
from tisem.io.semantickitti import SemanticKittiSequence
from tisem.labels import CLASS_NAMES
from tisem.scan import Scan

# Tiny example, worked out by hand (train ids: 1 car, 2 bicycle, 3 motorcycle, 5 other-vehicle).
#   idx   0  1  2  3  4  5  6  7  8  9
GT = [0, 0, 1, 1, 1, 1, 2, 2, 2, 3]
PRED = [1, 2, 1, 1, 2, 0, 2, 1, 5, 0]
# Points 0, 1 have GT 0: ignored entirely (their predictions 1, 2 are NOT false positives).
# Evaluated points: 8.
# car (1):        GT idx 2,3,4,5 -> pred 1,1,2,0: TP 2, FN 2 (one bicycle, one 0 = wrong);
#                 FP: idx 7 (GT bicycle, pred car) -> FP 1.          IoU 2/(2+1+2) = 0.4
# bicycle (2):    GT idx 6,7,8 -> pred 2,1,5: TP 1, FN 2; FP: idx 4 -> FP 1.  IoU 1/4 = 0.25
# motorcycle (3): GT idx 9 -> pred 0: TP 0, FN 1, FP 0.                      IoU 0
# other-vehicle (5): not in GT, predicted once (idx 8): TP 0, FP 1, FN 0 -> IoU 0.0, not present
# every other class: absent from GT and prediction -> None
TP = {1: 2, 2: 1, 3: 0, 5: 0}
FP = {1: 1, 2: 1, 3: 0, 5: 1}
FN = {1: 2, 2: 2, 3: 1, 5: 0}
GT_COUNT = {1: 4, 2: 3, 3: 1}


def test_hand_example_matrix_and_counts():
    c = Confusion().add(np.array(GT), np.array(PRED))
    m = c.matrix
    assert m.dtype == np.int64 and m.shape == (20, 20)
    expected = np.zeros((20, 20), np.int64)
    expected[1, 1] = 2
    expected[1, 2] = 1
    expected[1, 0] = 1
    expected[2, 2] = 1
    expected[2, 1] = 1
    expected[2, 5] = 1
    expected[3, 0] = 1
    np.testing.assert_array_equal(m, expected)
    tp, fp, fn = c.tp_fp_fn()
    for cls in range(20):
        assert tp[cls] == TP.get(cls, 0), cls
        assert fp[cls] == FP.get(cls, 0), cls
        assert fn[cls] == FN.get(cls, 0), cls


def test_hand_example_metrics():
    met = Confusion().add(GT, PRED).metrics()
    assert met["points"] == 8
    assert met["present_classes"] == ["car", "bicycle", "motorcycle"]
    assert met["miou"] == pytest.approx((0.4 + 0.25 + 0.0) / 3, abs=1e-15)
    assert met["miou_all"] == pytest.approx((0.4 + 0.25) / 19, abs=1e-15)
    assert met["accuracy"] == pytest.approx(3 / 8, abs=1e-15)
    assert met["wiou"] == pytest.approx((4 * 0.4 + 3 * 0.25 + 1 * 0.0) / 8, abs=1e-15)
    assert met["oa_paper"] == pytest.approx(
        (2 + 1 + 0 + 0) / ((2 + 1 + 2) + (1 + 1 + 2) + 1 + 1), abs=1e-15
    )
    pc = met["per_class_iou"]
    assert list(pc) == list(CLASS_NAMES[1:])
    assert pc["car"] == pytest.approx(0.4)
    assert pc["bicycle"] == pytest.approx(0.25)
    assert pc["motorcycle"] == 0.0
    assert pc["other-vehicle"] == 0.0  # predicted, absent from GT: 0, not None
    assert all(
        pc[n] is None
        for n in CLASS_NAMES[1:]
        if n not in ("car", "bicycle", "motorcycle", "other-vehicle")
    )
    assert not any(isinstance(v, float) and np.isnan(v) for v in pc.values())


def _reference_metrics(gt: np.ndarray, pred: np.ndarray, C: int = 20) -> dict:
    """numpy-only reference from boolean masks, independent of the confusion matrix."""
    ev = gt != 0
    gt, pred = gt[ev], pred[ev]
    iou, tps, unions, counts = {}, 0, 0, {}
    for c in range(1, C):
        tp = np.sum((gt == c) & (pred == c))
        fp = np.sum((gt != c) & (pred == c))
        fn = np.sum((gt == c) & (pred != c))
        tps += tp
        unions += tp + fp + fn
        iou[c] = tp / (tp + fp + fn) if tp + fp + fn else None
        counts[c] = np.sum(gt == c)
    present = [c for c in range(1, C) if counts[c] > 0]
    return {
        "miou": np.mean([iou[c] for c in present]),
        "miou_all": np.mean([iou[c] or 0.0 for c in range(1, C)]),
        "accuracy": np.mean(gt == pred),
        "wiou": sum(iou[c] * counts[c] for c in present) / sum(counts[c] for c in present),
        "oa_paper": tps / unions,
        "per_class_iou": iou,
        "points": int(ev.sum()),
    }


def test_matches_numpy_reference_on_random_labels():
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 12, 5000)  # classes 12..19 absent from GT
    pred = np.where(rng.random(5000) < 0.6, gt, rng.integers(0, 15, 5000))
    ref = _reference_metrics(gt, pred)
    # pool in two chunks + merge: same as one add
    a = Confusion().add(gt[:1234], pred[:1234])
    b = Confusion().add(gt[1234:], pred[1234:])
    met = a.merge(b).metrics()
    np.testing.assert_array_equal(a.matrix, Confusion().add(gt, pred).matrix)
    for key in ("miou", "miou_all", "accuracy", "wiou", "oa_paper"):
        assert met[key] == pytest.approx(ref[key], abs=1e-12), key
    assert met["points"] == ref["points"]
    for c in range(1, 20):
        got = met["per_class_iou"][CLASS_NAMES[c]]
        assert (got is None) == (ref["per_class_iou"][c] is None)
        if got is not None:
            assert got == pytest.approx(ref["per_class_iou"][c], abs=1e-12)


def test_empty_and_invalid():
    met = Confusion().metrics()
    assert met["points"] == 0
    assert met["miou"] is None and met["accuracy"] is None and met["oa_paper"] is None
    assert all(v is None for v in met["per_class_iou"].values())
    c = Confusion().add([0, 0], [3, 4])  # only GT 0: nothing evaluated
    assert c.metrics()["points"] == 0
    with pytest.raises(ValueError, match="3 ground-truth labels but 2"):
        Confusion().add([1, 2, 3], [1, 2])
    with pytest.raises(ValueError, match=r"predicted train ids must lie in \[0, 20\)"):
        Confusion().add([1, 2], [1, 20])
    with pytest.raises(ValueError, match="ground-truth"):
        Confusion().add([-1, 2], [1, 2])
    with pytest.raises(ValueError, match="cannot merge"):
        Confusion().merge(Confusion(num_classes=5))


def test_format_table_and_per_class():
    met = Confusion().add(GT, PRED).metrics()
    empty = Confusion().metrics()
    table = format_table([("hand", met), ("none", empty)])
    lines = table.splitlines()
    assert lines[0].startswith("| method | mIoU")
    assert "accuracy" in lines[0] and "wIoU" in lines[0] and "OA" in lines[0]
    assert lines[2] == "| hand | 0.2167 | 0.3750 | 0.2938 | 0.2727 |"
    assert lines[3] == "| none | – | – | – | – |"
    t2 = format_table([("hand", met)], columns=("miou_all", "points"))
    assert t2.splitlines()[2] == "| hand | 0.0342 | 8 |"

    pc = format_per_class([("a", met), ("b", met)])
    rows = {line.split(" | ")[0].lstrip("| "): line for line in pc.splitlines()}
    assert rows["car"] == "| car | 0.4000 | 0.4000 |"
    assert rows["motorcycle"] == "| motorcycle | 0.0000 | 0.0000 |"
    assert "other-vehicle *" in rows  # predicted only: marked
    assert "truck" not in rows  # absent everywhere: left out
    assert "| **mIoU (GT-present)** | 0.2167 | 0.2167 |" in pc
    assert "absent from the ground truth" in pc


def test_confusion_rebuilt_from_its_matrix():
    conf = Confusion(4).add(np.array([1, 1, 2, 3, 0]), np.array([1, 2, 2, 0, 3]))
    again = Confusion.from_matrix(conf.matrix.tolist())  # e.g. read back from JSON
    np.testing.assert_array_equal(again.matrix, conf.matrix)
    assert again.num_classes == 4 and again.metrics() == conf.metrics()
    again.add(np.array([3]), np.array([3]))  # and it goes on counting
    assert again.matrix[3, 3] == 1 and conf.matrix[3, 3] == 0
    for bad in (np.zeros((3, 4), np.int64), -np.ones((3, 3), np.int64), np.full((3, 3), 0.5)):
        with pytest.raises(ValueError):
            Confusion.from_matrix(bad)


def test_score_scan_ignores_non_finite_points_and_reads_probabilities():
    points = np.array([[1, 0, 0], [np.nan, 0, 0], [0, 2, 0], [0, 0, np.inf]], np.float32)
    probs = np.zeros((4, 4), np.float32)
    probs[[0, 1, 2], [1, 2, 3]] = 1.0  # point 3: no probability at all
    scan = Scan(points, np.eye(4), 0.0, probs=probs, gt_labels=np.array([1, 1, 2, 3]))
    labels = network_labels(scan)
    assert labels.tolist() == [1, 2, 3, 0]
    conf = Confusion(4)
    score_scan(conf, scan, labels)
    assert conf.metrics()["points"] == 2  # the NaN and the inf point: not scored
    assert conf.matrix[1, 1] == 1 and conf.matrix[2, 3] == 1


def test_network_predictions_on_real_data(kitti_mini):
    """The network predictions alone on the real frames: mIoU(present) 0.3881, accuracy 0.8497,
    15 GT-present classes (the reference figures of the project's specification)."""
    conf = Confusion()
    for scan in SemanticKittiSequence(kitti_mini, input="predictions"):
        conf.add(scan.gt_labels, scan.labels)
    met = conf.metrics()
    assert met["miou"] == pytest.approx(0.3881, abs=5e-4)
    assert met["accuracy"] == pytest.approx(0.8497, abs=5e-4)
    assert len(met["present_classes"]) == 15
    assert set(met["present_classes"]) == {
        "car",
        "road",
        "sidewalk",
        "building",
        "vegetation",
        "trunk",
        "terrain",
        "fence",
        "pole",
        "traffic-sign",
        "person",
        "parking",
        "bicycle",
        "other-ground",
        "bicyclist",
    }
    # GT as input scores perfectly (GT 0 is ignored, every other point is its own label)
    conf_gt = Confusion()
    for scan in SemanticKittiSequence(kitti_mini, input="labels"):
        conf_gt.add(scan.gt_labels, scan.labels)
    assert conf_gt.metrics()["miou"] == 1.0 and conf_gt.metrics()["accuracy"] == 1.0
