"""Point-wise accuracy of semantic labels.

The confusion matrix is pooled over every evaluated point: rows are ground-truth train ids,
columns predicted train ids. Conventions:

* GT train id 0 (unlabeled / outlier / other-*) is ignored entirely: such points are not
  evaluated and add no false positive to any class.
* A prediction of 0 (no map voxel, or an unlabeled input) is always wrong: it is a false
  negative of the point's GT class and a false positive of nothing.
* For a class c in 1..19: ``TP = M[c, c]``, ``FN = sum(M[c, :]) - TP`` (includes predictions
  of 0), ``FP = sum(M[1:, c]) - TP``, ``IoU = TP / (TP + FP + FN)``.

Metrics (`Confusion.metrics()`):

``miou``         mean IoU over the classes 1..19 *present in the GT* (GT count > 0); the
                 SemanticKITTI-style headline number of this project.
``miou_all``     mean IoU over all 19 classes 1..19; a class absent from the GT counts as IoU 0
                 (a class absent from GT *and* prediction too), so it is always <= ``miou`` on
                 partial data and comparable only between runs on the same scans.
``accuracy``     correct points / evaluated points (GT != 0).
``wiou``         IoU of each GT-present class weighted by its GT point count.
``oa_paper``     the paper's overall accuracy, ``sum TP / sum (TP + FP + FN)`` over 1..19.
``per_class_iou`` class name -> IoU for 1..19; ``None`` when the class is absent from both the
                 GT and the prediction (IoU undefined); 0.0 for a class predicted but absent
                 from GT (such a class is not in ``miou``).
``present_classes`` names of the GT-present classes; ``points`` the evaluated point count.

With no evaluated points the ratio metrics are ``None``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from tisem.labels import NUM_CLASSES, class_names
from tisem.scan import Scan, finite_rows

__all__ = [
    "Confusion",
    "format_table",
    "format_per_class",
    "METRIC_NAMES",
    "score_scan",
    "network_labels",
]

METRIC_NAMES = {
    "miou": "mIoU (GT-present classes)",
    "miou_all": "mIoU (all 19 classes, absent = 0)",
    "accuracy": "accuracy",
    "wiou": "wIoU (GT-count weighted)",
    "oa_paper": "OA (paper: ΣTP/Σ(TP+FP+FN))",
    "points": "evaluated points",
}


class Confusion:
    """Pooled int64 confusion matrix over train ids (rows GT, columns prediction)."""

    def __init__(self, num_classes: int = NUM_CLASSES):
        if num_classes < 2:
            raise ValueError(f"num_classes must be >= 2, got {num_classes}")
        self.num_classes = int(num_classes)
        self._m = np.zeros((self.num_classes, self.num_classes), dtype=np.int64)

    @classmethod
    def from_matrix(cls, matrix) -> Confusion:
        """A confusion holding the counts of `matrix` (C x C, rows GT, columns prediction),
        e.g. the `matrix` of one saved with a run's progress."""
        m = np.asarray(matrix)
        if m.ndim != 2 or m.shape[0] != m.shape[1]:
            raise ValueError(f"a confusion matrix must be square, got shape {m.shape}")
        if not np.issubdtype(m.dtype, np.integer) or (m.size and m.min() < 0):
            raise ValueError(
                f"a confusion matrix holds non-negative integer counts, got {m.dtype} values"
            )
        conf = cls(m.shape[0])
        conf._m += m.astype(np.int64)
        return conf

    # ------------------------------------------------------------------ accumulate
    def add(self, gt_train: np.ndarray, pred_train: np.ndarray) -> Confusion:
        """Count one batch of points; GT 0 is skipped. Returns self."""
        gt = np.asarray(gt_train).ravel()
        pred = np.asarray(pred_train).ravel()
        if gt.shape != pred.shape:
            raise ValueError(f"{gt.size} ground-truth labels but {pred.size} predictions")
        if gt.size == 0:
            return self
        C = self.num_classes
        for what, a in (("ground-truth", gt), ("predicted", pred)):
            lo, hi = int(a.min()), int(a.max())
            if lo < 0 or hi >= C:
                raise ValueError(f"{what} train ids must lie in [0, {C}), got [{lo}, {hi}]")
        keep = gt != 0
        gt = gt[keep].astype(np.int64)
        pred = pred[keep].astype(np.int64)
        self._m += np.bincount(gt * C + pred, minlength=C * C).reshape(C, C)
        return self

    def merge(self, other: Confusion) -> Confusion:
        """Add another confusion's counts into this one. Returns self."""
        if other.num_classes != self.num_classes:
            raise ValueError(
                f"cannot merge {other.num_classes}-class into {self.num_classes}-class confusion"
            )
        self._m += other._m
        return self

    @property
    def matrix(self) -> np.ndarray:
        """(C, C) int64 counts, rows GT, columns prediction (a copy). Row 0 is always zero."""
        return self._m.copy()

    # ------------------------------------------------------------------ metrics
    def tp_fp_fn(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-class TP, FP, FN (int64, length C; entry 0 is always 0)."""
        m = self._m
        tp = np.diag(m).copy()
        fn = m.sum(axis=1) - tp
        fp = m[1:, :].sum(axis=0) - tp
        tp[0] = fp[0] = fn[0] = 0  # class 0 is never scored
        return tp, fp, fn

    def gt_counts(self) -> np.ndarray:
        """GT points per class (int64, length C; entry 0 is 0: GT 0 is not counted)."""
        return self._m.sum(axis=1)

    def metrics(self) -> dict:
        tp, fp, fn = self.tp_fp_fn()
        gt = self.gt_counts()
        cls = np.arange(1, self.num_classes)
        union = tp + fp + fn
        iou = np.zeros(self.num_classes, dtype=np.float64)
        nz = union > 0
        iou[nz] = tp[nz] / union[nz]
        present = cls[gt[cls] > 0]
        points = int(gt.sum())
        names = [_class_name(c) for c in range(self.num_classes)]

        def ratio(a, b):
            return float(a) / float(b) if b > 0 else None

        return {
            "miou": float(iou[present].mean()) if present.size else None,
            "miou_all": float(iou[cls].mean()) if points else None,
            "accuracy": ratio(tp[cls].sum(), points),
            "wiou": ratio((iou[present] * gt[present]).sum(), gt[present].sum()),
            "oa_paper": ratio(tp[cls].sum(), union[cls].sum()),
            "per_class_iou": {names[c]: (float(iou[c]) if union[c] > 0 else None) for c in cls},
            "present_classes": [names[c] for c in present],
            "points": points,
        }

    def __repr__(self) -> str:
        m = self.metrics()
        f = lambda v: "n/a" if v is None else f"{v:.4f}"  # noqa: E731
        return f"Confusion({m['points']} points, mIoU {f(m['miou'])}, accuracy {f(m['accuracy'])})"


def network_labels(scan: Scan) -> np.ndarray:
    """The network's own per-point answer, scored like the map's (probabilities -> argmax; a
    point without any probability is unlabeled)."""
    if scan.labels is not None:
        return scan.labels
    labels = np.argmax(scan.probs, axis=1).astype(np.int32)
    labels[scan.probs.sum(axis=1) <= 0] = 0
    return labels


def online_labels(map_labels: np.ndarray, scan: Scan, dynamic: np.ndarray | None) -> np.ndarray:
    """A scan's answer right after it is mapped: the map's label per point, and for the points
    free space flagged dynamic the network's own (the map keeps nothing of them)."""
    if dynamic is None or not dynamic.any():
        return map_labels
    out = np.array(map_labels, copy=True)
    out[dynamic] = network_labels(scan)[dynamic]
    return out


def score_scan(conf: Confusion, scan: Scan, labels: np.ndarray) -> None:
    """Add one answer per point of `scan` to `conf`; non-finite points are no measurement, so
    they are not scored (the mapper drops them by the same rule, `finite_rows`)."""
    finite = finite_rows(scan.points_sensor)
    if finite.all():
        conf.add(scan.gt_labels, labels)
    else:
        conf.add(scan.gt_labels[finite], labels[finite])


def _class_name(c: int) -> str:
    names = class_names()  # the active label space's
    return names[c] if c < len(names) else f"class-{c}"


# --------------------------------------------------------------------------- tables


def _fmt(v, digits: int = 4) -> str:
    if v is None:
        return "–"
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return f"{int(v):,}"
    if isinstance(v, (float, np.floating)):
        return "–" if not np.isfinite(v) else f"{float(v):.{digits}f}"
    return str(v)


def _md_row(cells: Iterable[str]) -> str:
    return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"


def format_table(
    rows: Sequence[tuple[str, dict]],
    columns: Sequence[str] = ("miou", "accuracy", "wiou", "oa_paper"),
    name_header: str = "method",
    digits: int = 4,
) -> str:
    """A markdown table: one row per (name, metrics dict), one column per metric key.

    Column headers use the descriptive names in `METRIC_NAMES` (unknown keys as given);
    missing or undefined values print as "–".
    """
    lines = [
        _md_row([name_header] + [METRIC_NAMES.get(c, c) for c in columns]),
        _md_row(["---"] + ["---:"] * len(columns)),
    ]
    for name, metrics in rows:
        lines.append(_md_row([name] + [_fmt(metrics.get(c), digits) for c in columns]))
    return "\n".join(lines)


def format_per_class(rows: Sequence[tuple[str, dict]], digits: int = 4) -> str:
    """A markdown per-class IoU table: one row per class, one column per (name, metrics).

    Classes undefined in every row (absent from GT and prediction) are left out; a class that
    is absent from the GT of any row is marked with "*" (it is not part of that row's mIoU).
    The last row is the mIoU over GT-present classes.
    """
    if not rows:
        return ""
    class_names: list[str] = []
    for _, m in rows:
        for name in m.get("per_class_iou", {}):
            if name not in class_names:
                class_names.append(name)
    lines = [
        _md_row(["class"] + [name for name, _ in rows]),
        _md_row(["---"] + ["---:"] * len(rows)),
    ]
    marked = False
    for cname in class_names:
        values = [m.get("per_class_iou", {}).get(cname) for _, m in rows]
        if all(v is None for v in values):
            continue
        absent = any(cname not in m.get("present_classes", []) for _, m in rows)
        marked |= absent
        lines.append(
            _md_row([cname + (" *" if absent else "")] + [_fmt(v, digits) for v in values])
        )
    lines.append(
        _md_row(["**mIoU (GT-present)**"] + [_fmt(m.get("miou"), digits) for _, m in rows])
    )
    text = "\n".join(lines)
    if marked:
        text += "\n\n\\* absent from the ground truth (predicted only): not part of the mIoU."
    return text
