"""The continuous map's answer between its voxels, in numpy (no Taichi).

A point whose voxel holds no evidence gets the sum, over the voxels with evidence whose centres
lie within the query radius R, of g(d / R) times the voxel's normalised counters (g: the sparse
kernel of Melkumyan and Ramos). `kernels/query.py` computes the same on the live map; this is
the answer of maps held otherwise (a tiled map, the store beyond the live window, the numpy
reference).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

# neighbour cells looked at in one piece (~24 MB of int64 keys): each point looks at
# (2 reach + 1)^3 cells, 125 at the default radius
PIECE_CELLS = 1 << 20


def sparse_kernel(r: np.ndarray) -> np.ndarray:
    """Melkumyan-Ramos g(r), 0 for r >= 1."""
    r = np.asarray(r, dtype=np.float64)
    g = (2 + np.cos(2 * np.pi * r)) / 3 * (1 - r) + np.sin(2 * np.pi * r) / (2 * np.pi)
    return np.where(r < 1, np.maximum(g, 0.0), 0.0)


def blended_posterior(
    centres: np.ndarray, posterior: np.ndarray, points: np.ndarray, radius_m: float
) -> np.ndarray:
    """(N, C) for N points: `centres` (M, 3) and `posterior` (M, C) are the voxels with
    evidence (their centres in metres, their normalised counters)."""
    out = np.zeros((len(points), posterior.shape[1]))
    if not len(centres) or not len(points):
        return out
    near_each = cKDTree(centres).query_ball_point(np.asarray(points, np.float64), r=radius_m)
    for i, near in enumerate(near_each):
        if near:
            d = np.linalg.norm(centres[near] - points[i], axis=1)
            out[i] = (sparse_kernel(d / radius_m)[:, None] * posterior[near]).sum(axis=0)
    return out


def blend_by_lookup(
    points: np.ndarray,
    resolution_m: float,
    radius_m: float,
    posterior_of: Callable[[np.ndarray], np.ndarray],
) -> np.ndarray:
    """The same (N, C) blend, from a map that looks voxels up by key: `posterior_of(keys)`
    (K, 3) int64 world voxel keys -> (K, C) their normalised counters, zeros for a voxel
    without evidence or seen empty. Each point's cells within reach are looked up once."""
    points = np.asarray(points, np.float64)
    reach = int(np.ceil(radius_m / resolution_m))
    steps = np.arange(-reach, reach + 1)
    offsets = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), -1).reshape(-1, 3)
    piece = max(1, PIECE_CELLS // len(offsets))
    out = []
    for at in range(0, len(points), piece):
        pts = points[at : at + piece]
        keys = np.floor(pts / resolution_m).astype(np.int64)
        around = keys[:, None, :] + offsets[None, :, :]  # (K, (2 reach + 1)^3, 3)
        dist = np.linalg.norm((around + 0.5) * resolution_m - pts[:, None, :], axis=2)
        point, slot = np.nonzero(dist < radius_m)
        near, which = np.unique(around[point, slot], axis=0, return_inverse=True)
        weight = sparse_kernel(dist[point, slot] / radius_m)
        # row i: the sum over point i's neighbours of g(d / R) times their posterior
        spread = csr_matrix((weight, (point, which.ravel())), shape=(len(pts), len(near)))
        out.append(np.asarray(spread @ np.asarray(posterior_of(near), np.float64)))
    return np.concatenate(out) if out else np.zeros((0, 0))


def answer_blend(
    points: np.ndarray,
    rows: np.ndarray,
    resolution_m: float,
    radius_m: float,
    posterior_of: Callable[[np.ndarray], np.ndarray],
    labels: np.ndarray,
    probs: np.ndarray | None,
) -> None:
    """Points `rows` of `points` take their blend (`blend_by_lookup`) where it holds
    anything: its argmax into `labels` and, unless `probs` is None, its normalised values;
    the others keep their answer (0)."""
    if not len(rows):
        return
    acc = blend_by_lookup(points[rows], resolution_m, radius_m, posterior_of)
    sums = acc.sum(axis=1)
    got = sums > 0
    labels[rows[got]] = np.argmax(acc[got], axis=1)
    if probs is not None:
        probs[rows[got]] = acc[got] / sums[got, None]
