"""A network's error profile: how often each class is wrong (by range, at class boundaries),
what it is taken for, and how moving objects are labelled — fitted from measured counts.

The counts come from `tisem.synth.calibration` (an `ErrorStatistics`); the default profile is
fitted from those of the real network on SemanticKITTI 08 frames 0-4, stored in
`tisem.synth.kitti08_counts`. Five frames are few, so the fit smooths:

- P(wrong | class, range bin, boundary) is a logistic model: a logit per range bin, an
  offset per class, an offset per (class, range bin), and a boundary offset (one for all plus
  one per class), the class and cell offsets ridge-shrunk towards 0. A class the frames never
  show gets the pooled range profile; a (class, bin) cell with few points stays near the
  additive model, and a class seen at some ranges only is extrapolated by it. The ridge
  weights are in units of Fisher information (points x p (1 - p)): CLASS_RIDGE 5 weighs as
  ~40 points at p = 0.15, CELL_RIDGE 50 as ~400 — errors come in patches of tens to thousands
  of points, so five frames hold far fewer independent samples than points, and a class's
  range profile is the weakest part of the evidence.
- P(label | wrong, class) is the measured row plus WRONG_LABEL_PRIOR_POINTS pseudo-points
  spread over the plausible confusions (PLAUSIBLE_CONFUSIONS) — all a class absent from the
  frames has.
- Moving objects (raw 252-259) get their own error rate and wrong-label row, shrunk towards
  their static class with MOVER_PRIOR_POINTS pseudo-points.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from tisem.labels import CLASS_NAMES, LEARNING_MAP, NUM_CLASSES

CLASS_RIDGE = 5.0
CELL_RIDGE = 50.0
WRONG_LABEL_PRIOR_POINTS = 50.0
MOVER_PRIOR_POINTS = 200.0
MOVING_RAW_IDS = tuple(range(252, 260))

# What each class is plausibly mistaken for (relative weights): the prior of the wrong labels.
PLAUSIBLE_CONFUSIONS: dict[str, dict[str, float]] = {
    "car": {"truck": 0.5, "other-vehicle": 0.5},
    "bicycle": {"motorcycle": 0.6, "bicyclist": 0.4},
    "motorcycle": {"bicycle": 0.6, "motorcyclist": 0.4},
    "truck": {"car": 0.6, "other-vehicle": 0.4},
    "other-vehicle": {"car": 0.5, "truck": 0.5},
    "person": {"bicyclist": 0.5, "pole": 0.25, "trunk": 0.25},
    "bicyclist": {"person": 0.6, "bicycle": 0.4},
    "motorcyclist": {"motorcycle": 0.6, "bicyclist": 0.4},
    "road": {"parking": 0.5, "sidewalk": 0.5},
    "parking": {"road": 0.6, "sidewalk": 0.4},
    "sidewalk": {"road": 0.35, "terrain": 0.45, "parking": 0.2},
    "other-ground": {"sidewalk": 0.5, "terrain": 0.5},
    "building": {"fence": 0.75, "vegetation": 0.25},
    "fence": {"building": 0.6, "vegetation": 0.4},
    "vegetation": {"terrain": 0.55, "trunk": 0.45},
    "trunk": {"vegetation": 0.6, "pole": 0.4},
    "terrain": {"vegetation": 0.5, "sidewalk": 0.5},
    "pole": {"trunk": 0.6, "traffic-sign": 0.4},
    "traffic-sign": {"pole": 0.7, "building": 0.3},
}


@dataclass(frozen=True)
class NetworkProfile:
    """Per-point error probabilities and wrong-label draws.

    Rows 0..C-1 of the tables are the train ids; rows C.. the moving raw ids 252.. in order
    (`row_of`), which have one error rate for every range and no boundary offset.
    """

    range_centres_m: np.ndarray  # (B,) where the logits of `error_logit` hold
    error_logit: np.ndarray  # (C + 8, B) logit P(wrong) away from class boundaries
    boundary_logit: np.ndarray  # (C + 8,) added at a class boundary (0 for the movers)
    wrong_label_cdf: np.ndarray  # (C + 8, C) cumulative P(label | wrong), label ascending

    @staticmethod
    def row_of(gt_train: np.ndarray, mover_raw: np.ndarray | None) -> np.ndarray:
        """Table row of each point: its train id, or its moving raw id's row."""
        rows = np.asarray(gt_train, dtype=np.int64)
        if mover_raw is None:
            return rows
        moving = mover_raw > 0
        return np.where(moving, NUM_CLASSES + mover_raw.astype(np.int64) - MOVING_RAW_IDS[0], rows)

    def error_probability(
        self, rows: np.ndarray, range_m: np.ndarray, at_boundary: np.ndarray
    ) -> np.ndarray:
        """P(wrong) per point: the row's logit interpolated in range (held beyond the first
        and last centre), plus the boundary offset."""
        c = self.range_centres_m
        j = np.clip(np.searchsorted(c, range_m) - 1, 0, len(c) - 2)
        t = np.clip((range_m - c[j]) / (c[j + 1] - c[j]), 0.0, 1.0)
        logit = (1 - t) * self.error_logit[rows, j] + t * self.error_logit[rows, j + 1]
        logit = logit + self.boundary_logit[rows] * at_boundary
        return 1.0 / (1.0 + np.exp(-logit))

    def wrong_label(self, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The wrong label of each row for uniform draws u in [0, 1) (inverse CDF)."""
        k = (u[:, None] >= self.wrong_label_cdf[rows]).sum(axis=1)
        return np.minimum(k, NUM_CLASSES - 1)


def fit_profile(
    confusion: np.ndarray,
    cell_points: np.ndarray,
    cell_errors: np.ndarray,
    raw_predictions: dict,
    range_edges_m,
) -> NetworkProfile:
    """The profile of measured counts (`ErrorStatistics` fields of the same names)."""
    edges = np.asarray(range_edges_m, dtype=np.float64)
    table, boundary = fit_error_logits(cell_points, cell_errors)
    q = wrong_label_rows(confusion)
    class_rate = _class_error_rate(table, cell_points)
    mover_logit, mover_q = [], []
    for raw in MOVING_RAW_IDS:
        static = LEARNING_MAP[raw]
        counts = np.asarray(raw_predictions.get(raw, np.zeros(NUM_CLASSES)), dtype=np.float64)
        n, wrong = counts.sum(), counts.sum() - counts[static]
        p = (wrong + MOVER_PRIOR_POINTS * class_rate[static]) / (n + MOVER_PRIOR_POINTS)
        mover_logit.append(np.full(len(edges) - 1, np.log(p / (1 - p))))
        off = counts.copy()
        off[static] = 0.0
        off[0] = 0.0
        mover_q.append((off + MOVER_PRIOR_POINTS * q[static]) / (off.sum() + MOVER_PRIOR_POINTS))
    cdf = np.cumsum(np.vstack([q, np.array(mover_q)]), axis=1)
    cdf[:, -1] = 1.0  # no draw u < 1 falls past the last class
    return NetworkProfile(
        range_centres_m=(edges[:-1] + edges[1:]) / 2,
        error_logit=np.vstack([table, np.array(mover_logit)]),
        boundary_logit=np.append(boundary, np.zeros(len(MOVING_RAW_IDS))),
        wrong_label_cdf=cdf,
    )


def fit_error_logits(
    cell_points: np.ndarray, cell_errors: np.ndarray, sweeps: int = 1000, tolerance: float = 1e-6
) -> tuple[np.ndarray, np.ndarray]:
    """Ridge-penalised logistic fit of P(wrong) over (class, range bin, boundary) cells.

    logit = beta[bin] + alpha[class] + delta[class, bin] + (gamma + kappa[class]) * boundary.
    Returns the (C, B) table beta + alpha + delta (away from boundaries) and the (C,) boundary
    offsets gamma + kappa. Block coordinate Newton: within each group of parameters the
    Hessian is diagonal, so a step is a few sums (no linear solve, whose BLAS thread pool
    would cost far more than the arithmetic on shared cores); the penalised log-likelihood is
    strictly concave, so the sweeps converge.
    """
    n, w = cell_points.astype(np.float64), cell_errors.astype(np.float64)
    C, B, _ = n.shape
    d = np.array([0.0, 1.0])
    beta, alpha, delta = np.zeros(B), np.zeros(C), np.zeros((C, B))
    gamma, kappa = np.zeros(1), np.zeros(C)
    # each group: its parameters, the cell weights it multiplies, the axes its sums run
    # over (all others are the parameter's own), its ridge
    groups = (
        (beta, 1.0, (0, 2), 1e-6),
        (alpha, 1.0, (1, 2), CLASS_RIDGE),
        (delta, 1.0, (2,), CELL_RIDGE),
        (gamma, d, (0, 1, 2), 1e-6),
        (kappa, d, (1, 2), CLASS_RIDGE),
    )
    for _ in range(sweeps):
        largest = 0.0
        for theta, x, axes, ridge in groups:
            eta = (
                beta[None, :, None]
                + alpha[:, None, None]
                + delta[:, :, None]
                + (gamma + kappa)[:, None, None] * d
            )
            p = 1.0 / (1.0 + np.exp(-eta))
            grad = (x * (w - n * p)).sum(axis=axes).reshape(theta.shape) - ridge * theta
            hess = (x * x * n * p * (1 - p)).sum(axis=axes).reshape(theta.shape) + ridge
            step = np.clip(grad / hess, -4.0, 4.0)
            theta += step
            largest = max(largest, float(np.abs(step).max()))
        # moves that leave every logit as it is and only lower the ridge penalty: without
        # them the coordinate steps crawl along these flat directions (one class's data
        # cannot tell its offset from the bins')
        shift = alpha.mean()
        alpha -= shift
        beta += shift
        shift = delta.mean(axis=0)
        delta -= shift
        beta += shift
        shift = (CELL_RIDGE * delta.sum(axis=1) - CLASS_RIDGE * alpha) / (
            CLASS_RIDGE + B * CELL_RIDGE
        )
        alpha += shift
        delta -= shift[:, None]
        shift = kappa.mean()
        kappa -= shift
        gamma += shift
        if largest < tolerance:
            break
    return beta[None, :] + alpha[:, None] + delta, gamma + kappa


def wrong_label_rows(confusion: np.ndarray) -> np.ndarray:
    """(C, C) P(label | wrong, true class): the measured off-diagonal counts plus
    WRONG_LABEL_PRIOR_POINTS pseudo-points over the plausible confusions. Never 0, never the
    true class; a class with neither gets its wrong labels uniformly."""
    off = np.asarray(confusion, dtype=np.float64).copy()
    np.fill_diagonal(off, 0.0)
    off[:, 0] = 0.0
    prior = np.zeros_like(off)
    for name, row in PLAUSIBLE_CONFUSIONS.items():
        total = sum(row.values())
        for other, weight in row.items():
            prior[CLASS_NAMES.index(name), CLASS_NAMES.index(other)] = weight / total
    rows = off + WRONG_LABEL_PRIOR_POINTS * prior
    empty = rows.sum(axis=1) == 0
    rows[empty, 1:] = 1.0
    rows[np.arange(NUM_CLASSES), np.arange(NUM_CLASSES)] = 0.0
    return rows / rows.sum(axis=1, keepdims=True)


def _class_error_rate(table: np.ndarray, cell_points: np.ndarray) -> np.ndarray:
    """(C,) the fitted P(wrong) of each class over its measured range mix (pooled mix for a
    class without points), away from boundaries."""
    mix = cell_points.sum(axis=2).astype(np.float64)
    pooled = mix.sum(axis=0)
    mix[mix.sum(axis=1) == 0] = pooled
    mix /= mix.sum(axis=1, keepdims=True)
    return (mix / (1.0 + np.exp(-table))).sum(axis=1)


# ---------------------------------------------------------------------------- stored counts
# The counts a profile is fitted from, as a small Python module of literals (class names,
# not ids, so that it reads as a table): see tisem/synth/kitti08_counts.py.


def write_counts_module(stats, path, title: str) -> None:
    """Write the counts of `stats` (a `tisem.synth.calibration.ErrorStatistics`) that a
    profile is fitted from as a Python module."""
    from tisem.synth.calibration import RANGE_EDGES_M

    names = CLASS_NAMES

    def sparse(head: str, counts) -> list[str]:
        """`head {name: count, ...},` packed into lines of at most 100 characters."""
        items = [f'"{names[k]}": {int(v)}' for k, v in enumerate(counts) if v]
        out, line = [], f"    {head}{{"
        for k, item in enumerate(items):
            piece = item + ("}," if k == len(items) - 1 else ",")
            if len(line) + len(piece) + 1 > 100:
                out.append(line)
                line = "        " + piece
            else:
                line += ("" if line.endswith("{") else " ") + piece
        return out + [line]

    lines = [
        f'"""{title}',
        "",
        "Written by benchmarks/noise_calibration.py --write-counts; read by",
        'tisem.synth.profile. Counts only: no points, no labels of any scan."""',
        "",
        f"RANGE_EDGES_M = {tuple(float(e) for e in RANGE_EDGES_M)}",
        "",
        "# true class -> {predicted class: points}",
        "CONFUSION = {",
    ]
    for c, row in enumerate(stats.confusion):
        if row.sum():
            lines += sparse(f'"{names[c]}": ', row)
    lines += [
        "}",
        "",
        "# true class -> per range bin: points inside, points at a class boundary,",
        "# errors inside, errors at a boundary",
        "CELLS = {",
    ]
    for c in range(NUM_CLASSES):
        if stats.cell_points[c].sum():
            rows = [
                stats.cell_points[c, :, 0],
                stats.cell_points[c, :, 1],
                stats.cell_errors[c, :, 0],
                stats.cell_errors[c, :, 1],
            ]
            lines.append(f'    "{names[c]}": (')
            lines += [f"        {tuple(int(v) for v in r)}," for r in rows]
            lines.append("    ),")
    lines += ["}", "", "# raw ground-truth id -> {predicted class: points}", "RAW_PREDICTIONS = {"]
    for raw, counts in stats.raw_predictions.items():
        if counts.sum():
            lines += sparse(f"{raw}: ", counts)
    lines += ["}", ""]
    Path(path).write_text("\n".join(lines))


def counts_from_module(module) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """(confusion, cell_points, cell_errors, raw_predictions) of a counts module."""
    index = {n: i for i, n in enumerate(CLASS_NAMES)}

    def dense(sparse: dict) -> np.ndarray:
        out = np.zeros(NUM_CLASSES, dtype=np.int64)
        for name, v in sparse.items():
            out[index[name]] = v
        return out

    confusion = np.zeros((NUM_CLASSES, NUM_CLASSES), dtype=np.int64)
    for name, row in module.CONFUSION.items():
        confusion[index[name]] = dense(row)
    bins = len(module.RANGE_EDGES_M) - 1
    points, errors = np.zeros((2, NUM_CLASSES, bins, 2), dtype=np.int64)
    for name, (p_in, p_edge, e_in, e_edge) in module.CELLS.items():
        c = index[name]
        points[c, :, 0], points[c, :, 1], errors[c, :, 0], errors[c, :, 1] = (
            p_in,
            p_edge,
            e_in,
            e_edge,
        )
    raw = {int(r): dense(row) for r, row in module.RAW_PREDICTIONS.items()}
    return confusion, points, errors, raw


@lru_cache(maxsize=1)
def kitti08_profile() -> NetworkProfile:
    """The profile of the real network on SemanticKITTI 08 frames 0-4 (the default)."""
    from tisem.synth import kitti08_counts

    return fit_profile(*counts_from_module(kitti08_counts), kitti08_counts.RANGE_EDGES_M)
