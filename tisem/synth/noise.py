""""Network" predictions: ground truth corrupted the way a LiDAR segmentation network errs.

Errors come from four sources, all in train-id space:
- a per-point rate that grows with range (sparse, far points are hard);
- class boundaries in the range image — a network's labels bleed across edges, so a point
  with a differently labelled neighbour often takes that neighbour's class;
- coherent blobs: random spheres in the world, redrawn every scan, inside which one
  confusable class replaces the true one (the temporally flickering patches a mapper should
  smooth away);
- whole instances: now and then a car is taken for a truck, a person for a bicyclist.
Every wrong label is a *plausible* one (CONFUSIONS), and no prediction is ever 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tisem.labels import CLASS_NAMES, NUM_CLASSES

# What each class is mistaken for, and how often relative to the others.
CONFUSIONS: dict[str, dict[str, float]] = {
    "car": {"truck": 0.5, "other-vehicle": 0.5},
    "truck": {"car": 0.6, "other-vehicle": 0.4},
    "other-vehicle": {"car": 0.5, "truck": 0.5},
    "person": {"bicyclist": 1.0},
    "bicyclist": {"person": 1.0},
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


def _confusion_table():
    """(C, K) targets and cumulative weights; a class without entries maps to itself."""
    width = max(len(v) for v in CONFUSIONS.values())
    targets = np.tile(np.arange(NUM_CLASSES)[:, None], (1, width))
    cdf = np.ones((NUM_CLASSES, width))
    for name, row in CONFUSIONS.items():
        c = CLASS_NAMES.index(name)
        w = np.array(list(row.values()))
        targets[c, :len(row)] = [CLASS_NAMES.index(n) for n in row]
        cdf[c, :len(row)] = np.cumsum(w / w.sum())
    return targets, cdf


_TARGETS, _CDF = _confusion_table()


def confuse(gt_train: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The confusable class of each gt_train picked by a uniform draw u (same shape, or a
    scalar: one draw shared by a whole region gives one coherent mistake per class)."""
    u = np.broadcast_to(u, gt_train.shape)
    k = (u[:, None] > _CDF[gt_train]).sum(axis=1)
    return _TARGETS[gt_train, np.minimum(k, _TARGETS.shape[1] - 1)]


def boundary_neighbour(gt_train: np.ndarray, ring: np.ndarray, col: np.ndarray,
                       image_shape: tuple[int, int], half_rings: int = 1,
                       half_cols: int = 2) -> np.ndarray:
    """For each point, the class of a range-image neighbour with another class, else -1.

    The neighbourhood is (2 half_rings + 1) x (2 half_cols + 1) pixels; columns wrap (the
    sensor spins), rings do not; empty pixels (misses) do not count.
    """
    rings, cols = image_shape
    image = np.full(image_shape, -1, dtype=np.int16)
    image[ring, col] = gt_train
    other = np.full(len(gt_train), -1, dtype=np.int64)
    for dr in range(-half_rings, half_rings + 1):
        rr = ring + dr
        ok = (rr >= 0) & (rr < rings)
        rr = np.clip(rr, 0, rings - 1)
        for dc in range(-half_cols, half_cols + 1):
            if dr == 0 and dc == 0:
                continue
            nb = image[rr, (col + dc) % cols]
            new = ok & (nb >= 0) & (nb != gt_train) & (other < 0)
            other[new] = nb[new]
    return other


@dataclass(frozen=True)
class NoiseModel:
    """Rates tuned so that the predictions score ~0.84 accuracy against ground truth."""

    base_rate: float = 0.06          # everywhere
    far_rate: float = 0.30           # added at max range, growing with (range / max range)^2
    boundary_rate: float = 0.30      # added at a range-image class boundary
    bleed_prob: float = 0.7          # a boundary error takes the neighbour's class
    num_blobs: int = 18              # coherent error spheres per scan
    blob_radius_m: tuple[float, float] = (1.0, 3.5)
    blob_reach_m: float = 40.0       # blob centres lie within this distance of the sensor
    blob_swap_prob: float = 0.85     # share of points inside a blob that take its mistake
    instance_swap_prob: float = 0.08  # chance per scan that an object is mistaken whole

    def apply(self, gt_train: np.ndarray, ring: np.ndarray, col: np.ndarray,
              image_shape: tuple[int, int], range_m: np.ndarray, max_range_m: float,
              points_world: np.ndarray, instance: np.ndarray, sensor_xyz: np.ndarray,
              rng: np.random.Generator) -> np.ndarray:
        """Predicted train ids (int64) for one scan."""
        n = len(gt_train)
        pred = gt_train.astype(np.int64).copy()
        other = boundary_neighbour(gt_train, ring, col, image_shape)
        at_edge = other >= 0
        p = (self.base_rate + self.far_rate * (range_m / max_range_m) ** 2
             + self.boundary_rate * at_edge)
        wrong = rng.random(n) < p
        bleed = wrong & at_edge & (rng.random(n) < self.bleed_prob)
        pred[bleed] = other[bleed]
        plain = wrong & ~bleed
        pred[plain] = confuse(gt_train[plain], rng.random(int(plain.sum())))

        for region in self._regions(points_world, instance, sensor_xyz, rng):
            swap = region[rng.random(region.size) < self.blob_swap_prob]
            pred[swap] = confuse(gt_train[swap], rng.random())
        return pred

    def _regions(self, points_world, instance, sensor_xyz, rng):
        """Point indices of the scan's coherent error regions: blobs, then mistaken instances."""
        angle = rng.uniform(0, 2 * np.pi, self.num_blobs)
        dist = self.blob_reach_m * np.sqrt(rng.random(self.num_blobs))    # uniform in a disc
        centres = np.column_stack([sensor_xyz[0] + dist * np.cos(angle),
                                   sensor_xyz[1] + dist * np.sin(angle),
                                   rng.uniform(0.0, 4.0, self.num_blobs)])
        radii = rng.uniform(*self.blob_radius_m, self.num_blobs)
        # points sorted by x: each blob only looks at the slab |x - centre x| < radius
        order = np.argsort(points_world[:, 0], kind="stable")
        xs = points_world[order, 0]
        for c, r in zip(centres, radii):
            cand = order[np.searchsorted(xs, c[0] - r):np.searchsorted(xs, c[0] + r)]
            yield np.sort(cand[((points_world[cand] - c) ** 2).sum(axis=1) < r * r])
        ids = np.unique(instance[instance > 0])
        for i in ids[rng.random(len(ids)) < self.instance_swap_prob]:
            yield np.flatnonzero(instance == i)
