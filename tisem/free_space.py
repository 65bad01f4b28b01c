"""The free-space step of the mapper: what moved is found, flagged and cleared.

Per scan, with `free_space: true`:

* before the scan changes the map, its points that land in a live voxel observed empty, or
  where the map holds no voxel in space a ray crossed less than seen_empty_s ago (unless they
  border space no ray has seen, or are of a class that cannot move next to a live voxel their
  class leads: kernels/raycast.py), are flagged dynamic (DUFOMap's rule: space
  seen empty at one time makes anything in it at another time dynamic), and so are the points
  the input's motion labels call moving (`Scan.moving`): flagged points add no evidence to the
  map, so what drives through space seen empty leaves no trail; with dynamic_clusters, the
  flags of a mover's points are spread over its whole cluster (tisem/dynamic_clusters.py), and
  its flagged points still end rays;
* after the kernel update, every voxel holding a training point gains a hit, and one ray per
  `free_ray_stride` training points, from the sensor to a margin before it, takes occupancy
  evidence from every live voxel it crosses, except voxels next to a hit of the scan and
  (spare_beside_unseen) voxels next to space no ray has seen (kernels/raycast.py). A voxel at
  or below
  -empty_evidence is empty: queries answer it as no voxel, exports leave it out of the static
  map.

Free space never makes a voxel live, so the map's memory is what it is without it, plus the
memory of space seen empty (kernels/seen_empty.py: seconds of it, forgotten in passes, never
stored); the occupancy evidence travels with the voxel to the store, checkpoints and map
files.

Per-class decay (`tau_movable_s`, st mode) is independent of free space: the movable classes'
counters fade with their own tau, so a parked car's evidence yields to what is seen there next.
"""

from __future__ import annotations

import collections
import dataclasses

import numpy as np
from taichi.lang.argpack import ArgPack

from tisem.config import MapperConfig
from tisem.dynamic_clusters import spread_over_clusters
from tisem.kernels import raycast, seen_empty
from tisem.kernels.layout import MapFields
from tisem.kernels.params import EXPONENTIAL, FORGET, PER_CLASS
from tisem.labels import MOVABLE_CLASSES
from tisem.live_window import ivec
from tisem.preprocess import CheckedScan
from tisem.scan import to_frame
from tisem.scan_buffers import TrainingRows


def decay_rule(cfg: MapperConfig) -> str:
    """The map's decay rule (kernels/params.py): per class when the movable classes have a
    tau of their own."""
    if cfg.decay_tau_s == 0:
        return FORGET
    return PER_CLASS if cfg.movable_tau_s != cfg.decay_tau_s else EXPONENTIAL


def class_inv_tau(cfg: MapperConfig) -> np.ndarray:
    """(C,) float32 1 / tau of every class (0 for tau = inf)."""

    def inv(tau: float) -> float:
        return 0.0 if tau in (0.0, float("inf")) else 1.0 / tau

    out = np.full(cfg.num_classes, inv(cfg.decay_tau_s), np.float32)
    movable = [c for c in MOVABLE_CLASSES if c < cfg.num_classes]
    out[movable] = inv(cfg.movable_tau_s)
    return out


def static_classes(num_classes: int) -> np.ndarray:
    """(C,) int32: 1 for a class that cannot move, 0 for the movable ones and class 0."""
    out = np.ones(num_classes, np.int32)
    out[[c for c in (0, *MOVABLE_CLASSES) if c < num_classes]] = 0
    return out


def without_moving(checked: CheckedScan, moving: np.ndarray) -> CheckedScan:
    """The scan with its moving points' evidence taken away (they still count as points)."""
    if not moving.any():
        return checked
    evidence = checked.evidence.copy()
    evidence[moving] = 0
    return dataclasses.replace(checked, evidence=evidence)


class FreeSpace:
    """The free-space step of one map (its fields and config)."""

    def __init__(
        self, fields: MapFields, cfg: MapperConfig, decay: str, window_half_vox: np.ndarray
    ):
        self._fields = fields
        static = static_classes(cfg.num_classes) == 1
        thin_static = cfg.thin_class_mask & static  # (the rays' spare, the clusters' joining)
        if fields.spare_static_beside_own:
            fields.static_class.from_numpy(static.astype(np.int32))
        if fields.spare_thin_static:
            fields.thin_static_class.from_numpy(thin_static.astype(np.int32))
        self._margin_m = float(cfg.free_margin_m)
        self._margin_fraction = float(cfg.free_margin_fraction)
        self._stride = int(cfg.free_ray_stride)
        self._mark_hits, self._cast_free, self._clear_crossed = raycast.free_space_kernels(decay)
        self._memory_s = fields.seen_empty_s
        # the sensor's voxel at the scans whose rays the memory may still hold, and how far it
        # may move from them before a storage cell of the memory could stand for another place
        self._recent: collections.deque = collections.deque()
        self._slack_vox = np.array(fields.N) - 2 * np.asarray(window_half_vox)
        self._next_forget_s = -np.inf
        self._blocks = 0  # the memory's blocks after its last pass
        # (movable classes, cluster_link_m, cluster_min_seeds, cluster_min_fraction, the
        # classes that join clusters or None) with dynamic_clusters, else None
        self._clusters = None
        if cfg.dynamic_clusters:
            movable = ~static
            movable[0] = False
            joining = thin_static if cfg.cluster_thin_classes else None
            self._clusters = (
                movable,
                float(cfg.cluster_link_m),
                int(cfg.cluster_min_seeds),
                float(cfg.cluster_min_fraction),
                joining,
            )
        self._dynamic_ends: np.ndarray | None = None  # (D, 3) local metres, float32
        self._max_range2 = float(cfg.max_range_m) ** 2
        self._resolution_m = float(cfg.resolution_m)

    def flag_points(
        self,
        params: ArgPack,
        checked: CheckedScan,
        half_vox: np.ndarray,
        moving: np.ndarray | None,
        to_local: tuple[np.ndarray, np.ndarray],
    ) -> np.ndarray:
        """(N,) bool: which points of the scan are dynamic, before the scan changes the map
        (`to_local`: T_world_sensor and the map origin in metres, for the clusters)."""
        flags = np.zeros(len(checked.points_sensor), np.int8)
        ev = checked.evidence
        labels = ev if not checked.use_probs else np.argmax(ev, axis=1)
        labels = np.ascontiguousarray(labels, np.int32)
        raycast.flag_dynamic(
            self._fields, params, checked.kernel_points, labels, ivec(half_vox), flags
        )
        dynamic = flags.astype(bool)
        self._dynamic_ends = None
        if self._clusters is not None:
            dynamic = spread_over_clusters(checked.points_sensor, labels, dynamic, *self._clusters)
            self._dynamic_ends = self._ray_ends(checked.points_sensor[dynamic], half_vox, to_local)
        if moving is not None:
            dynamic |= moving
        return dynamic

    def _ray_ends(
        self, points: np.ndarray, half_vox: np.ndarray, to_local: tuple[np.ndarray, np.ndarray]
    ) -> np.ndarray:
        """(D, 3) float32 local metres: every free_ray_stride-th of a scan's dynamic points
        (sensor frame), in range and in the live window, whose storage a ray must not wrap
        around. A mover's points add no evidence, but the space between the sensor and them
        is empty all the same: without these rays a car driving off along the line of sight
        would leave its old place uncleared."""
        T, origin_m = to_local
        sensor = points[:: self._stride]
        local = to_frame(sensor, T, origin_m)
        half_m = np.asarray(half_vox) * self._resolution_m
        inside = np.all(np.abs(local - (T[:3, 3] - origin_m)) <= half_m, axis=1)
        inside &= np.einsum("ij,ij->i", sensor, sensor) <= self._max_range2
        return local[inside].astype(np.float32)

    def integrate(self, params: ArgPack, rows: TrainingRows, n_rows: int) -> int:
        """Hits, then rays, of the scan's n_rows training points; returns how many voxels
        lost occupancy evidence."""
        if n_rows == 0:
            return 0
        self._mark_hits(self._fields, params, rows.xyz, n_rows)
        freed = self._cast_free(
            self._fields,
            params,
            rows.xyz,
            n_rows,
            self._stride,
            self._margin_m,
            self._margin_fraction,
        )
        ends = self._dynamic_ends
        if ends is not None and len(ends):
            freed += self._cast_free(
                self._fields, params, ends, len(ends), 1, self._margin_m, self._margin_fraction
            )
        if self._fields.spare_beside_unseen:
            freed += self._clear_crossed(self._fields, params)
        return int(freed)

    def forget_if_wrapped(self, time_rel_s: float, center_vox: np.ndarray) -> None:
        """Before a scan's flags: forget the whole memory of space seen empty when the sensor
        is so far from where it was at a scan the memory may still hold that a storage cell
        (toroidal, like the map's) would stand for another place."""
        if self._memory_s <= 0:
            return
        recent = self._recent
        while recent and recent[0][0] + self._memory_s <= time_rel_s:
            recent.popleft()
        center = np.asarray(center_vox, np.int64)
        if any(np.any(np.abs(center - c) >= self._slack_vox) for _, c in recent):
            # (every block expired by then; not snode.deactivate_all(), whose own kernel taichi
            # compiles with a warning per index)
            seen_empty.forget_expired_blocks(self._fields, float("inf"))
            seen_empty.forget_empty_tops(self._fields)
            recent.clear()
            self._blocks = 0
        recent.append((time_rel_s, center))

    def forget(self, time_rel_s: float) -> int:
        """After a scan's rays: the memory forgets what expired, in a pass over its blocks
        every quarter of its span (so it holds at most 5/4 of it); returns the blocks it held
        after the last pass."""
        if self._memory_s > 0 and time_rel_s >= self._next_forget_s:
            self._next_forget_s = time_rel_s + self._memory_s / 4
            self._blocks = int(seen_empty.forget_expired_blocks(self._fields, time_rel_s))
            seen_empty.forget_empty_tops(self._fields)
        return self._blocks
