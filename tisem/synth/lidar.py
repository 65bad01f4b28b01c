"""A 64-beam spinning LiDAR (HDL-64-like) ray-cast against the synthetic world, in numpy.

Rays form a (ring, column) grid: 64 fixed elevations x `points_per_ring` azimuths. The
sensor is level (the world is flat), so each primitive's bounding cylinder maps to a
rectangle of that grid — a column range from its azimuth extent and a ring range from its
elevation extent. Only the rays in those rectangles are intersected with the primitive,
which keeps a scan to a few hundred thousand ray/primitive pairs instead of 65k x hundreds.
The ground is the plane z = 0; its class comes from the world (a region mask on the plane).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from tisem.synth.shapes import Boxes, Cylinders, Ellipsoids, ShapeSet

# HDL-64E: an upper block of 32 beams at 1/3 degree spacing, a lower one at ~1/2 degree,
# +2.0 ... -24.8 degrees; ring 0 is the top beam.
HDL64_ELEVATIONS_DEG = np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)])

# Rough remission of each raw class (signs are retro-reflective, asphalt is dark); the
# sensor adds range fall-off and noise.
_REMISSION = np.zeros(260, dtype=np.float32)
for _raw, _value in {
    10: 0.25,
    252: 0.25,
    30: 0.3,
    40: 0.18,
    44: 0.22,
    48: 0.3,
    50: 0.32,
    51: 0.28,
    70: 0.42,
    71: 0.3,
    72: 0.38,
    80: 0.35,
    81: 0.85,
}.items():
    _REMISSION[_raw] = _value


def rotate(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """v @ R.T for (n, 3) v, written out: a BLAS matmul here starts a thread pool that spins
    on the shared cores and costs more CPU than the whole scan."""
    return v[:, :1] * R[:, 0] + v[:, 1:2] * R[:, 1] + v[:, 2:] * R[:, 2]


@dataclass
class Returns:
    """The hits of one scan, in ray order (ring-major)."""

    ring: np.ndarray  # (N,) int64, 0 = top beam
    col: np.ndarray  # (N,) int64 azimuth column
    range_m: np.ndarray  # (N,) float64, with range noise
    points: np.ndarray  # (N, 3) float32, LiDAR frame
    remission: np.ndarray  # (N,) float32
    label: np.ndarray  # (N,) uint32 raw ground-truth id
    instance: np.ndarray  # (N,) uint32


@dataclass(frozen=True)
class Lidar:
    points_per_ring: int = 1024
    max_range_m: float = 80.0
    min_range_m: float = 1.0
    range_noise_m: float = 0.02  # 1-sigma, Gaussian
    mount_height_m: float = 1.73  # KITTI's Velodyne above the ground

    @property
    def num_rings(self) -> int:
        return len(HDL64_ELEVATIONS_DEG)

    @cached_property
    def elevations(self) -> np.ndarray:
        return np.radians(HDL64_ELEVATIONS_DEG)

    @cached_property
    def directions(self) -> np.ndarray:
        """(rings * cols, 3) unit ray directions in the LiDAR frame; column c at azimuth
        2 pi c / cols."""
        az = 2 * np.pi * np.arange(self.points_per_ring) / self.points_per_ring
        el = self.elevations[:, None]
        return np.stack(
            np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)),
            axis=-1,
        ).reshape(-1, 3)

    def cast(
        self,
        shapes: ShapeSet,
        ground_label: Callable[[np.ndarray], np.ndarray],
        T_world_lidar: np.ndarray,
        rng: np.random.Generator,
    ) -> Returns:
        """Ray-cast one scan. ground_label(xy (n,2)) -> raw ids of ground hits."""
        origin = T_world_lidar[:3, 3]
        R = T_world_lidar[:3, :3]
        dirs = rotate(self.directions, R)
        n_rays = len(dirs)
        best_t = np.full(n_rays, np.inf)
        label = np.zeros(n_rays, dtype=np.uint32)
        instance = np.zeros(n_rays, dtype=np.uint32)

        # nearest primitive per ray: intersect the culled pairs, keep each ray's minimum
        rays, ts, labels, insts = [], [], [], []
        yaw = np.arctan2(R[1, 0], R[0, 0])
        for part in shapes.parts.values():
            if not len(part):
                continue
            idx, ray = self._candidate_pairs(part.footprint(), origin, yaw)
            t = ray_distances(part, idx, origin, dirs[ray])
            hit = t <= self.max_range_m
            rays.append(ray[hit]), ts.append(t[hit])
            labels.append(part.label[idx[hit]]), insts.append(part.instance[idx[hit]])
        if rays:
            ray, t = np.concatenate(rays), np.concatenate(ts)
            np.minimum.at(best_t, ray, t)
            win = t == best_t[ray]
            label[ray[win]] = np.concatenate(labels)[win]
            instance[ray[win]] = np.concatenate(insts)[win]

        # the ground plane z = 0, where no primitive is nearer
        dz = dirs[:, 2]
        with np.errstate(divide="ignore"):
            t_ground = np.where(dz < 0, -origin[2] / dz, np.inf)
        ground = (t_ground < best_t) & (t_ground <= self.max_range_m)
        best_t[ground] = t_ground[ground]
        label[ground] = ground_label(origin[:2] + dirs[ground, :2] * t_ground[ground, None])
        instance[ground] = 0

        hit = np.flatnonzero(best_t <= self.max_range_m)
        # noise moves a return along its ray; clipping keeps every point inside the range band
        r = np.clip(
            best_t[hit] + rng.normal(0.0, self.range_noise_m, hit.size),
            self.min_range_m,
            self.max_range_m,
        )
        lab = label[hit]
        remission = np.clip(
            _REMISSION[lab] * (1.0 - 0.35 * r / self.max_range_m) + rng.normal(0.0, 0.04, hit.size),
            0.0,
            1.0,
        ).astype(np.float32)
        return Returns(
            ring=hit // self.points_per_ring,
            col=hit % self.points_per_ring,
            range_m=r,
            points=(self.directions[hit] * r[:, None]).astype(np.float32),
            remission=remission,
            label=lab,
            instance=instance[hit],
        )

    def _candidate_pairs(self, footprint, origin, yaw):
        """(primitive index, ray index) of every ray inside each primitive's grid rectangle."""
        cxy, radius, z0, z1 = footprint
        cols = self.points_per_ring
        dx, dy = cxy[:, 0] - origin[0], cxy[:, 1] - origin[1]
        d = np.hypot(dx, dy)
        near = np.flatnonzero(d - radius < self.max_range_m)
        cxy, radius, z0, z1, dx, dy, d = (a[near] for a in (cxy, radius, z0, z1, dx, dy, d))
        inside = d <= radius  # the sensor inside a footprint: every azimuth
        half = np.arcsin(np.clip(radius / np.maximum(d, 1e-9), 0.0, 1.0))
        az = np.arctan2(dy, dx) - yaw
        step = 2 * np.pi / cols
        c0 = np.where(inside, 0, np.ceil((az - half) / step)).astype(np.int64)
        c1 = np.where(inside, cols - 1, np.floor((az + half) / step)).astype(np.int64)
        n_col = np.clip(c1 - c0 + 1, 0, cols)
        # elevation extent: atan2(z, d) is monotonic in d, so the extremes are at the nearest
        # and farthest horizontal distances of the footprint
        d_near, d_far = np.maximum(d - radius, 1e-3), d + radius
        oz = origin[2]
        e_lo = np.minimum(np.arctan2(z0 - oz, d_near), np.arctan2(z0 - oz, d_far))
        e_hi = np.maximum(np.arctan2(z1 - oz, d_near), np.arctan2(z1 - oz, d_far))
        ascending = self.elevations[::-1]
        a_lo = np.searchsorted(ascending, e_lo, side="left")
        n_ring = np.searchsorted(ascending, e_hi, side="right") - a_lo
        counts = n_col * n_ring
        prim = np.repeat(np.arange(len(near)), counts)
        local = np.arange(prim.size) - np.repeat(np.cumsum(counts) - counts, counts)
        n_ring_p = n_ring[prim]
        col = (c0[prim] + local // n_ring_p) % cols
        ring = self.num_rings - 1 - (a_lo[prim] + local % n_ring_p)
        return near[prim], ring * cols + col


# ----------------------------------------------------------------------------- intersections
# Each takes the primitives, a primitive index and a world direction per pair, and the shared
# ray origin; it returns the entry distance per pair (inf for a miss).


def _t_boxes(b: Boxes, idx, origin, d):
    c, s = np.cos(b.yaw[idx]), np.sin(b.yaw[idx])
    q = origin - b.center[idx]
    # into the box frame (rotate by -yaw), then the slab test
    q_local = (c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1], q[:, 2])
    d_local = (c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2])
    t_near = np.full(len(idx), -np.inf)
    t_far = np.full(len(idx), np.inf)
    for axis in range(3):
        da = d_local[axis]
        inv = 1.0 / np.where(np.abs(da) < 1e-12, 1e-12, da)
        h = b.half[idx, axis]
        t1, t2 = (-h - q_local[axis]) * inv, (h - q_local[axis]) * inv
        t_near = np.maximum(t_near, np.minimum(t1, t2))
        t_far = np.minimum(t_far, np.maximum(t1, t2))
    return np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)


def _t_cylinders(cy: Cylinders, idx, origin, d):
    q = origin[:2] - cy.center[idx]
    r = cy.radius[idx]
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    bh = q[:, 0] * d[:, 0] + q[:, 1] * d[:, 1]  # half of the usual b
    c = q[:, 0] ** 2 + q[:, 1] ** 2 - r**2
    disc = bh**2 - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-bh - np.sqrt(disc)) / a
        z = origin[2] + t * d[:, 2]
        side = (disc >= 0) & (a > 1e-12) & (t > 0) & (z >= cy.z0[idx]) & (z <= cy.z1[idx])
        # the top cap, seen from above (short cylinders below the sensor)
        t_top = (cy.z1[idx] - origin[2]) / d[:, 2]
        xy = q + t_top[:, None] * d[:, :2]
        top = (d[:, 2] < 0) & (t_top > 0) & (xy[:, 0] ** 2 + xy[:, 1] ** 2 <= r**2)
    return np.minimum(np.where(side, t, np.inf), np.where(top, t_top, np.inf))


def _t_ellipsoids(e: Ellipsoids, idx, origin, d):
    # scale space so the ellipsoid is the unit sphere; t is unchanged by the scaling
    radii = e.radii[idx]
    q = (origin - e.center[idx]) / radii
    ds = d / radii
    a = np.einsum("ij,ij->i", ds, ds)
    bh = np.einsum("ij,ij->i", q, ds)
    c = np.einsum("ij,ij->i", q, q) - 1.0
    disc = bh**2 - a * c
    with np.errstate(invalid="ignore"):
        t = (-bh - np.sqrt(disc)) / a
    return np.where((disc >= 0) & (t > 0), t, np.inf)


_INTERSECT = {Boxes: _t_boxes, Cylinders: _t_cylinders, Ellipsoids: _t_ellipsoids}


def ray_distances(
    part: Boxes | Cylinders | Ellipsoids, idx: np.ndarray, origin: np.ndarray, dirs: np.ndarray
) -> np.ndarray:
    """Distance along each unit direction dirs[k] from origin to primitive idx[k] of `part`
    (Boxes, Cylinders or Ellipsoids), inf where the ray misses it."""
    return _INTERSECT[type(part)](part, idx, origin, dirs)
