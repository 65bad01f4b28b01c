"""Sub-voxel class boundaries on the host: the query rule of kernels/centroids.py for voxels in
the store, in map files and tiles, and the merge of two maps' slots.

A voxel's class centroids are CENTROID_COLS float32 columns, two slots of (class, weight, x, y,
z): the two classes with the most evidence among the voxel's own points and the mean offset of
their points from the voxel's low corner, metres. A query point in a voxel whose second class
holds at least `ratio` of its leading class's evidence takes the class whose centroid is nearer,
when both classes hold a slot.
"""

from __future__ import annotations

import numpy as np

# a voxel's class centroids: two slots of (class, weight, x, y, z)
SLOT = 5
CENTROID_COLS = 2 * SLOT
# two classes whose points lie within this many voxels of each other in the voxel mark no
# boundary (mixed through the voxel, or equal to float error): the voxel answers its argmax
MIN_SEPARATION = 0.05


def centroid_problem(centroids: np.ndarray, voxels: int, num_classes: int) -> str | None:
    """What makes `centroids` unfit for a map of `voxels` voxels and `num_classes` classes (a
    kernel indexes by a slot's class, and Taichi does not check indices), or None."""
    if centroids.shape != (voxels, CENTROID_COLS):
        return f"centroids must be ({voxels}, {CENTROID_COLS}), got {centroids.shape}"
    if not np.isfinite(centroids).all():
        return "centroids must be finite"
    cls = centroids[:, [0, SLOT]]
    if np.any((cls < 0) | (cls >= num_classes) | (cls != np.floor(cls))):
        return f"a centroid slot's class must be a whole number in [0, {num_classes})"
    if np.any(centroids[:, [1, SLOT + 1]] < 0):
        return "a centroid slot's weight must not be negative"
    return None


def slot_classes(centroids: np.ndarray) -> np.ndarray:
    """(M, 2) int: the class of each slot (0: empty)."""
    return centroids[:, [0, SLOT]].astype(np.int64)


def slot_means(centroids: np.ndarray) -> np.ndarray:
    """(M, 2, 3): each slot's mean offset in its voxel, metres."""
    return np.stack([centroids[:, 2:SLOT], centroids[:, SLOT + 2 :]], axis=1)


def two_leading(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(best, second): per row the argmax of `counts` and the argmax of the rest (the first on
    a tie, as the query kernel picks them)."""
    rows = np.arange(len(counts))
    best = np.argmax(counts, axis=1)
    rest = counts.copy()
    rest[rows, best] = -np.inf
    return best, np.argmax(rest, axis=1) if counts.shape[1] > 1 else best


def split_labels(
    counts: np.ndarray,
    centroids: np.ndarray,
    offsets: np.ndarray,
    ratio: float,
    labels: np.ndarray,
    resolution_m: float,
) -> np.ndarray:
    """`labels` (the voxels' own answers for the M query points, rows of `counts` and
    `centroids`) with the nearer-centroid rule applied where it splits the voxel; `offsets`
    (M, 3): each point's offset from its voxel's low corner, metres. float32 throughout, as in
    the kernel."""
    out = np.array(labels, copy=True)
    if not len(out):
        return out
    counts = np.asarray(counts, np.float32)
    best, second = two_leading(counts)
    rows = np.arange(len(counts))
    best_v, second_v = counts[rows, best], counts[rows, second]
    split = (out == best) & (second_v > 0) & (second_v >= np.float32(ratio) * best_v)
    cls = slot_classes(centroids)
    wgt = centroids[:, [1, SLOT + 1]]
    kb = np.where(cls[:, 0] == best, 0, 1)
    ks = 1 - kb
    held = (cls[rows, kb] == best) & (cls[rows, ks] == second) & (wgt[rows, kb] > 0)
    held &= wgt[rows, ks] > 0
    split &= held
    means = slot_means(np.asarray(centroids, np.float32))
    off = np.asarray(offsets, np.float32)
    d_best = np.square(off - means[rows, kb]).sum(axis=1)
    d_second = np.square(off - means[rows, ks]).sum(axis=1)
    sep = np.square(means[rows, kb] - means[rows, ks]).sum(axis=1)
    far = sep > np.float32(MIN_SEPARATION * resolution_m) ** 2
    take = split & far & (d_second < d_best)
    out[take] = second[take]
    return out


def merge_slots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M, CENTROID_COLS): the slots of two maps' voxels (rows of `a` and `b` are the same
    voxels) as one: a class in both adds up (weighted mean), and the two heaviest of the
    (up to four) classes keep a slot. Exact for the class a voxel's points agree on; a class
    that one map wore down and the other kept is weighed by what each holds now."""
    m = len(a)
    cls = np.concatenate([slot_classes(a), slot_classes(b)], axis=1)  # (M, 4)
    wgt = np.concatenate([a[:, [1, SLOT + 1]], b[:, [1, SLOT + 1]]], axis=1).astype(np.float64)
    pos = np.concatenate([slot_means(a), slot_means(b)], axis=1).astype(np.float64)  # (M, 4, 3)
    wgt[cls == 0] = 0.0
    # fold each of b's slots into a's slot of the same class
    for j in (2, 3):
        for i in (0, 1):
            same = (cls[:, j] == cls[:, i]) & (wgt[:, j] > 0) & (wgt[:, i] > 0)
            total = np.where(same, wgt[:, i] + wgt[:, j], wgt[:, i])
            mix = np.where(
                same[:, None], wgt[:, i, None] * pos[:, i] + wgt[:, j, None] * pos[:, j], 0
            )
            pos[:, i] = np.where(
                same[:, None], mix / np.where(total > 0, total, 1)[:, None], pos[:, i]
            )
            wgt[:, i] = total
            wgt[same, j] = 0.0
    order = np.argsort(-wgt, axis=1, kind="stable")[:, :2]  # the two heaviest
    rows = np.arange(m)
    out = np.zeros((m, CENTROID_COLS), np.float32)
    for k in range(2):
        pick = order[:, k]
        keep = wgt[rows, pick] > 0
        out[:, k * SLOT] = np.where(keep, cls[rows, pick], 0)
        out[:, k * SLOT + 1] = np.where(keep, wgt[rows, pick], 0.0)
        out[:, k * SLOT + 2 : k * SLOT + 5] = np.where(keep[:, None], pos[rows, pick], 0.0)
    return out
