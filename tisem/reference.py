"""A plain numpy implementation of the method: the oracle the kernels are tested
against, and the baseline the throughput benchmark measures its speedup over.

It follows the same rules as `tisem.mapper.Mapper` with none of its machinery: a dict of voxels,
`np.unique` rasterisation, a k-d tree for the kernel neighbourhoods, float64 throughout.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from tisem.blend import blended_posterior, sparse_kernel
from tisem.class_centroids import CENTROID_COLS, SLOT, split_labels
from tisem.config import MapperConfig
from tisem.geometry import block_aligned_origin
from tisem.kernels.bki import MIN_UPDATE
from tisem.labels import MOVABLE_CLASSES
from tisem.map_clock import MapClock
from tisem.preprocess import select_points
from tisem.scan import Scan, scan_label, to_frame


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


def class_centroids_of(
    local: np.ndarray, sel, keys: np.ndarray, hist: np.ndarray, res: float
) -> np.ndarray:
    """(V, CENTROID_COLS): per voxel of `keys` (as `voxel_histograms` returns them, with its
    class evidence `hist`) its two leading classes (the lower on a tie) with their evidence
    and the mean offset of their points from the voxel's low corner."""
    inv = np.unique(np.floor(local / res).astype(np.int64), axis=0, return_inverse=True)[1]
    inv = inv.reshape(-1)
    order = np.argsort(-hist[:, 1:], axis=1, kind="stable")[:, :2] + 1
    out = np.zeros((len(keys), CENTROID_COLS))
    rows = np.arange(len(keys))
    for k in range(2):
        c = order[:, k]
        w_vox = hist[rows, c]
        c = np.where(w_vox > 0, c, 0)
        if sel.labels is not None:
            w = (sel.labels == c[inv]).astype(np.float64)
        else:
            w = sel.probs[np.arange(len(inv)), c[inv]].astype(np.float64)
        w[c[inv] == 0] = 0.0
        wsum = np.bincount(inv, w, len(keys))
        off = local - keys[inv] * res
        mean = np.stack([np.bincount(inv, w * off[:, a], len(keys)) for a in range(3)], 1)
        mean = np.divide(mean, wsum[:, None], out=np.zeros_like(mean), where=wsum[:, None] > 0)
        out[:, k * SLOT] = c
        out[:, k * SLOT + 1] = wsum
        out[:, k * SLOT + 2 : k * SLOT + 5] = mean
    return out


def merge_scan_slots(
    slots: np.ndarray, scan: np.ndarray, dt: np.ndarray, cfg: MapperConfig
) -> np.ndarray:
    """The map's slots of some voxels (rows of `slots`) after folding in one scan's (`scan`,
    from `class_centroids_of`), `dt` seconds after each voxel's last update: the rule of
    kernels/centroids.py, one voxel at a time."""
    out = np.array(slots, dtype=np.float64, copy=True)
    tau = [
        cfg.movable_tau_s if c in MOVABLE_CLASSES else cfg.decay_tau_s
        for c in range(cfg.num_classes)
    ]
    for i in range(len(out)):
        cls = [int(out[i, 0]), int(out[i, SLOT])]
        wgt = []
        for k in range(2):
            t = tau[cls[k]]
            a = 0.0 if t == 0 else 1.0 if math.isinf(t) else math.exp(-max(dt[i], 0.0) / t)
            wgt.append(a * out[i, k * SLOT + 1])
        pos = [out[i, 2:SLOT].copy(), out[i, SLOT + 2 :].copy()]
        for r in range(2):
            c, w = int(scan[i, r * SLOT]), scan[i, r * SLOT + 1]
            mean = scan[i, r * SLOT + 2 : r * SLOT + 5]
            if w <= 0:
                continue
            if c in cls:
                k = cls.index(c)
                pos[k] = (pos[k] * wgt[k] + mean * w) / (wgt[k] + w)
                wgt[k] += w
                continue
            j = 0 if wgt[0] <= wgt[1] else 1
            if w >= wgt[j]:
                cls[j], wgt[j], pos[j] = c, w, mean.copy()
            else:
                wgt[j] -= w
        for k in range(2):
            if wgt[k] <= 0:
                cls[k], wgt[k] = 0, 0.0
            out[i, k * SLOT] = cls[k]
            out[i, k * SLOT + 1] = wgt[k]
            out[i, k * SLOT + 2 : k * SLOT + 5] = pos[k]
    return out


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
        self.centroids = np.zeros((0, CENTROID_COLS))  # class centroids (class_centroids)
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
            self.centroids = np.vstack([self.centroids, np.zeros((n, CENTROID_COLS))])
        return ids

    def _layer_neighbours(self, keys: np.ndarray) -> np.ndarray:
        """Per voxel, how many map voxels lie among the 24 within 2 of it in its z layer."""
        offsets = [(dx, dy) for dx in range(-2, 3) for dy in range(-2, 3) if dx or dy]
        return np.array(
            [sum((x + dx, y + dy, z) in self.index for dx, dy in offsets) for x, y, z in keys],
            np.int64,
        )

    def rasterize(self, scan: Scan):
        """Steps 1-3: the kept voxels' keys, centroids and (weighted) class evidence, and
        their class centroids (`class_centroids_of`; None when the map keeps none)."""
        cfg = self.config
        sel = select_points(scan, cfg)
        T = scan.T_world_sensor
        if self.origin_vox is None:
            self.origin_vox = block_aligned_origin(np.floor(T[:3, 3] / self.res))
        local = to_frame(sel.points_sensor, T, self.origin_vox * self.res)
        keys, npts, centroid, hist = voxel_histograms(local, sel, self.res, self.C)
        total = hist.sum(axis=1)
        keep = (npts >= cfg.min_points) & (total > 0)
        slots = None
        if cfg.class_centroids:
            slots = class_centroids_of(local, sel, keys, hist, self.res)[keep]
        h = hist[keep]
        if cfg.point_weight == "unit":
            h = h / total[keep, None]
        return keys[keep], centroid[keep], h, slots

    @property
    def t0(self) -> float | None:
        return self.clock.state.t0

    def integrate(self, scan: Scan) -> None:
        t_rel = self.clock.time_of(scan.stamp_s, scan_label(scan.index, scan.name))
        keys, centroid, h, slots = self.rasterize(scan)
        self.clock.advance(scan.stamp_s, t_rel)
        if slots is not None:  # (before the fusion: it reads each voxel's previous time)
            ids = self._voxel_ids(keys)
            dt = t_rel - self.t_last_rel[ids]
            self.centroids[ids] = merge_scan_slots(self.centroids[ids], slots, dt, self.config)
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
            # a voxel holding a long_kernel class at long_kernel_share of its leading class's
            # evidence takes the longest kernel
            long = list(cfg.long_kernel_ids)
            if long:
                evidence = p - cfg.prior
                top = evidence[:, 1:].max(axis=1)
                held = evidence[:, long]
                outvoted = ((held > 0) & (held >= cfg.long_kernel_share * top[:, None])).any(1)
                if cfg.long_kernel_min_neighbours > 0:  # ... in a z layer that is wide there
                    wide = self._layer_neighbours(self.keys[ids[outvoted]])
                    outvoted[outvoted] = wide >= cfg.long_kernel_min_neighbours
                self.length_m[ids[outvoted]] = cfg.ell_max_m
        else:
            self.length_m[ids] = cfg.ell_fixed_vox * self.res
        # every map voxel with a training point within kernel_cutoff of its own kernel length
        # gets an update
        centres = (self.keys + 0.5) * self.res
        reach = self.length_m * cfg.kernel_cutoff
        tree = cKDTree(centroid)
        near = tree.query_ball_point(centres, r=reach)
        v_idx = np.repeat(np.arange(len(centres)), [len(n) for n in near])
        if len(v_idx) == 0:
            return
        p_idx = np.concatenate([np.asarray(n, np.int64) for n in near])
        d = np.linalg.norm(centroid[p_idx] - centres[v_idx], axis=1)
        inside = d < reach[v_idx]
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
        if self.config.class_centroids:
            rows = np.array([self.index.get(k, -1) for k in map(tuple, keys)])
            at = rows >= 0
            labels[at] = split_labels(
                self.counts[rows[at]],
                self.centroids[rows[at]],
                pts[at] - (keys[at] + self.origin_vox) * self.res,
                self.config.centroid_ratio,
                labels[at],
                self.res,
            )
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
        return blended_posterior(centres, posterior, points_world, radius)

    def voxel_centroids(self) -> np.ndarray:
        """(M, CENTROID_COLS) class centroids in the order of `voxels()`."""
        g = self.keys + self.origin_vox
        return self.centroids[np.lexsort((g[:, 2], g[:, 1], g[:, 0]))]

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
