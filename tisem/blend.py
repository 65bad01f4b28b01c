"""The continuous map's answer between its voxels, in numpy (no Taichi).

A point whose voxel holds no evidence gets the sum, over the voxels with evidence whose centres
lie within the query radius R, of g(d / R) times the voxel's normalised counters (g: the sparse
kernel of Melkumyan and Ramos). `kernels/query.py` computes the same on the live map; this is
the answer of maps held as arrays (a tiled map, the numpy reference).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


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
