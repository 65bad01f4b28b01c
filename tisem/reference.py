"""A plain numpy implementation of the method: the oracle the kernels are tested
against, and the baseline the throughput benchmark measures its speedup over.

It follows the same rules as `tisem.mapper.Mapper` with none of its machinery: a dict of voxels,
`np.unique` rasterisation, a k-d tree for the kernel neighbourhoods, float64 throughout.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from tisem.config import MapperConfig
from tisem.geometry import block_aligned_origin
from tisem.kernels.bki import MIN_UPDATE
from tisem.map_clock import MapClock
from tisem.preprocess import select_points
from tisem.scan import Scan, scan_label, to_frame


def sparse_kernel(r: np.ndarray) -> np.ndarray:
    """Melkumyan-Ramos g(r), 0 for r >= 1."""
    r = np.asarray(r, dtype=np.float64)
    g = (2 + np.cos(2 * np.pi * r)) / 3 * (1 - r) + np.sin(2 * np.pi * r) / (2 * np.pi)
    return np.where(r < 1, np.maximum(g, 0.0), 0.0)


def normalized_entropy(p: np.ndarray) -> np.ndarray:
    """Row-wise entropy over classes 1..C-1 of unnormalised p, divided by log(C-1)."""
    q = p[:, 1:] / p[:, 1:].sum(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -np.where(q > 0, q * np.log(q), 0.0).sum(axis=1)
    return h / math.log(p.shape[1] - 1)


def decay(dt: np.ndarray, cfg: MapperConfig) -> np.ndarray:
    tau = cfg.decay_tau_s
    if tau == 0:
        return np.zeros_like(dt)
    return np.exp(-np.maximum(dt, 0) / tau)


def voxel_histograms(xyz: np.ndarray, sel, res: float, num_classes: int):
    """Steps 1-2 in numpy: the voxels that the points `xyz` (any frame, float64) hit, as
    (keys, point counts, centroids, class histograms), sorted by key. `sel` carries the
    points' labels or probabilities (tisem.preprocess.select_points); class 0 adds no evidence."""
    keys, inv = np.unique(np.floor(xyz / res).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    nv = len(keys)
    npts = np.bincount(inv, minlength=nv)
    centroid = np.stack([np.bincount(inv, xyz[:, a], nv) for a in range(3)], 1) / npts[:, None]
    hist = np.zeros((nv, num_classes))
    if sel.labels is not None:
        ok = sel.labels > 0
        np.add.at(hist, (inv[ok], sel.labels[ok]), 1.0)
    else:
        p = sel.probs.astype(np.float64).copy()
        p[:, 0] = 0
        np.add.at(hist, inv, p)
    return keys, npts, centroid, hist


class ReferenceMapper:
    """Same interface as `Mapper` for integrate/query/snapshot-like access (no window)."""

    def __init__(self, config: MapperConfig | None = None):
        self.config = config or MapperConfig()
        self.config.validate()
        self.C = self.config.num_classes
        self.res = self.config.resolution_m
        self.index: dict[tuple, int] = {}
        self.keys = np.zeros((0, 3), np.int64)  # local voxel keys
        self.counts = np.zeros((0, self.C))
        self.t_last_rel = np.zeros(0)
        self.length_m = np.zeros(0)
        self.origin_vox = None
        self.clock = MapClock(self.config.decay_tau_s)  # the mapper's map time

    def _voxel_ids(self, keys: np.ndarray) -> np.ndarray:
        """Indices of the given voxels, creating the missing ones."""
        ids = np.empty(len(keys), np.int64)
        new = []
        for i, k in enumerate(map(tuple, keys)):
            j = self.index.get(k)
            if j is None:
                j = len(self.index)
                self.index[k] = j
                new.append(k)
            ids[i] = j
        if new:
            n = len(new)
            self.keys = np.vstack([self.keys, np.array(new, np.int64)])
            self.counts = np.vstack([self.counts, np.zeros((n, self.C))])
            self.t_last_rel = np.concatenate([self.t_last_rel, np.zeros(n)])
            self.length_m = np.concatenate([self.length_m, np.zeros(n)])
        return ids

    def rasterize(self, scan: Scan):
        """Steps 1-3: the kept voxels' keys, centroids and (weighted) class evidence."""
        cfg = self.config
        sel = select_points(scan, cfg)
        T = scan.T_world_sensor
        if self.origin_vox is None:
            self.origin_vox = block_aligned_origin(np.floor(T[:3, 3] / self.res))
        local = to_frame(sel.points_sensor, T, self.origin_vox * self.res)
        keys, npts, centroid, hist = voxel_histograms(local, sel, self.res, self.C)
        total = hist.sum(axis=1)
        keep = (npts >= cfg.min_points) & (total > 0)
        h = hist[keep]
        if cfg.point_weight == "unit":
            h = h / total[keep, None]
        return keys[keep], centroid[keep], h

    @property
    def t0(self) -> float | None:
        return self.clock.state.t0

    def integrate(self, scan: Scan) -> None:
        t_rel = self.clock.time_of(scan.stamp_s, scan_label(scan.index, scan.name))
        keys, centroid, h = self.rasterize(scan)
        self.clock.advance(scan.stamp_s, t_rel)
        self._fuse(keys, centroid, h, t_rel)

    def _fuse(self, keys: np.ndarray, centroid: np.ndarray, h: np.ndarray, t_rel: float) -> None:
        """Steps 4-8 for one scan's training points at map time t_rel."""
        cfg = self.config
        ids = self._voxel_ids(keys)
        if not cfg.uses_kernel:  # csm: plain per-voxel counting
            self.counts[ids] += h
            self.t_last_rel[ids] = t_rel
            self.length_m[ids] = cfg.ell_min_m if cfg.adaptive else cfg.ell_fixed_vox * self.res
            return
        if cfg.adaptive:
            alpha = decay(t_rel - self.t_last_rel[ids], cfg)
            p = cfg.prior + alpha[:, None] * self.counts[ids] + h
            span = cfg.ell_max_m - cfg.ell_min_m
            self.length_m[ids] = cfg.ell_min_m + span * normalized_entropy(p)
        else:
            self.length_m[ids] = cfg.ell_fixed_vox * self.res
        # every map voxel with a training point within its own kernel length gets an update
        centres = (self.keys + 0.5) * self.res
        tree = cKDTree(centroid)
        near = tree.query_ball_point(centres, r=self.length_m)
        v_idx = np.repeat(np.arange(len(centres)), [len(n) for n in near])
        if len(v_idx) == 0:
            return
        p_idx = np.concatenate([np.asarray(n, np.int64) for n in near])
        d = np.linalg.norm(centroid[p_idx] - centres[v_idx], axis=1)
        inside = d < self.length_m[v_idx]
        v_idx, p_idx, d = v_idx[inside], p_idx[inside], d[inside]
        # class c's evidence takes the kernel of length min(L(v), cap_c)
        caps = cfg.evidence_caps_m
        delta = np.zeros((len(centres), self.C))
        for c in range(1, self.C):
            w = cfg.sigma0 * sparse_kernel(d / np.minimum(self.length_m[v_idx], caps[c]))
            delta[:, c] = np.bincount(v_idx, w * h[p_idx, c], len(centres))
        upd = delta.sum(axis=1) > MIN_UPDATE
        alpha = decay(t_rel - self.t_last_rel[upd], cfg)
        self.counts[upd] = alpha[:, None] * self.counts[upd] + delta[upd]
        self.t_last_rel[upd] = t_rel

    def query(self, points_world: np.ndarray):
        """(labels, probabilities) of world points: the voxel's posterior; for a point in a
        voxel without evidence (query_blend missing) the blend of the voxels within
        query_radius_m; else 0 / zeros."""
        pts = np.asarray(points_world, np.float64)
        labels = np.zeros(len(pts), np.int32)
        probs = np.zeros((len(pts), self.C))
        if self.origin_vox is None:
            return labels, probs
        keys = np.floor(pts / self.res).astype(np.int64) - self.origin_vox
        missing = np.ones(len(pts), bool)
        for i, k in enumerate(map(tuple, keys)):
            j = self.index.get(k)
            if j is not None and self.counts[j].sum() > 0:
                labels[i] = int(np.argmax(self.counts[j]))
                probs[i] = self.counts[j] / self.counts[j].sum()
                missing[i] = False
        if self.config.query_blend == "missing" and missing.any():
            blend = self.blended_posterior(pts[missing])
            total = blend.sum(axis=1)
            labels[missing] = np.where(total > 0, blend.argmax(axis=1), 0)
            probs[missing] = blend / np.where(total > 0, total, 1.0)[:, None]
        return labels, probs

    def blended_posterior(self, points_world: np.ndarray) -> np.ndarray:
        """(N, C): sum over the voxels with evidence whose centres lie within query_radius_m
        of each point of g(d / R) times the voxel's normalised counters."""
        radius = self.config.query_radius_m
        total = self.counts.sum(axis=1)
        has = np.flatnonzero(total > 0)
        out = np.zeros((len(points_world), self.C))
        if not len(has):
            return out
        centres = (self.keys[has] + self.origin_vox + 0.5) * self.res
        posterior = self.counts[has] / total[has, None]
        for i, near in enumerate(cKDTree(centres).query_ball_point(points_world, r=radius)):
            if near:
                d = np.linalg.norm(centres[near] - points_world[i], axis=1)
                out[i] = (sparse_kernel(d / radius)[:, None] * posterior[near]).sum(axis=0)
        return out

    def voxels(self):
        """(global keys, counts, t_last, ell_m) sorted by key, like `Mapper.snapshot()`."""
        g = self.keys + self.origin_vox
        order = np.lexsort((g[:, 2], g[:, 1], g[:, 0]))
        return (
            g[order],
            self.counts[order],
            self.t_last_rel[order] + self.t0,
            self.length_m[order],
        )
