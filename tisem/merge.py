"""Merging maps built apart: the Bayesian counters of a voxel add up over any split of the scans.

With the lazy decay a voxel's counters at time T are sum_k exp(-(T - t_k) / tau) dsigma_k, so
two maps of disjoint sets of scans combine per voxel: decay each map's counters from its t_last
to the latest t_last of the voxel, add them, keep that latest time (and the kernel length of
the map that updated the voxel last). For tau = inf (csm, bki, adaptive) that is a plain sum;
for tau = 0 (spatial) the latest update wins.

    merged = merge_snapshots([snap_a, snap_b], [tau_a, tau_b])
    own = contribution(final, seed, tau)   # what a run added on top of the map it started from

How exact that is depends on the mode (docs/scale.md has the measurements): `csm` only adds
each training voxel's histogram, so a merge equals the serial map. In the kernel modes the
engine updates the voxels that exist when a scan arrives, so a map built apart misses the
kernel mass other logs' scans would have given to voxels only those logs created; a run seeded
with the map of the logs before it (`contribution` takes the seed back out) closes that gap
exactly for `bki`, and for `adaptive` / `st` as far as the seed is exact.
"""

from __future__ import annotations

import numpy as np

from tisem.class_centroids import SLOT, merge_slots
from tisem.snapshot import MapSnapshot
from tisem.tiles import pack_keys, take_rows

__all__ = [
    "merge_snapshots",
    "decay_factors",
    "contribution",
    "transform_snapshot",
    "check_compatible",
]


def decay_factors(dt_s: np.ndarray, tau_s: float) -> np.ndarray:
    """exp(-dt / tau) for dt >= 0: 1 for tau = inf, and for tau = 0 1 at dt = 0 else 0."""
    dt = np.maximum(np.asarray(dt_s, np.float64), 0.0)
    if tau_s == float("inf"):
        return np.ones_like(dt)
    if tau_s == 0:
        return (dt == 0).astype(np.float64)
    return np.exp(-dt / tau_s)


def merge_snapshots(parts: list[MapSnapshot], taus: list[float] | float) -> MapSnapshot:
    """One map of the voxels of every part: per voxel, each part's counters decayed (with that
    part's tau) to the voxel's latest t_last and summed; t_last the latest, the kernel length of
    the part that has it. Parts must share resolution and class count."""
    taus = [taus] * len(parts) if np.isscalar(taus) else list(taus)
    if len(taus) != len(parts):
        raise ValueError(f"{len(parts)} parts but {len(taus)} decay constants")
    kept = [(p, t) for p, t in zip(parts, taus) if len(p)]
    if not parts:
        raise ValueError("nothing to merge")
    if len(kept) <= 1:
        return kept[0][0] if kept else parts[0]
    res, num_classes = parts[0].resolution_m, parts[0].counts.shape[1]
    keys = np.concatenate([p.keys for p, _ in kept])
    t_last = np.concatenate([p.t_last for p, _ in kept])
    tau = np.concatenate([np.full(len(p), t) for p, t in kept])
    packed = pack_keys(keys)
    # by voxel, and within a voxel by time: the last row of a voxel is its latest update
    order = np.lexsort((t_last, packed))
    packed, t_last, tau = packed[order], t_last[order], tau[order]
    starts = np.flatnonzero(np.r_[True, packed[1:] != packed[:-1]])
    ends = np.r_[starts[1:], len(packed)] - 1
    voxel_of_row = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(packed)]))
    dt = t_last[ends][voxel_of_row] - t_last
    factor = np.ones(len(dt))
    for value in np.unique(tau):
        rows = tau == value
        factor[rows] = decay_factors(dt[rows], float(value))
    counts = np.concatenate([p.counts for p, _ in kept])[order].astype(np.float64)
    summed = np.add.reduceat(counts * factor[:, None], starts, axis=0)
    ell = np.concatenate([p.ell_m for p, _ in kept])[order]
    merged = MapSnapshot(keys[order][ends], summed.astype(np.float32), t_last[ends], ell[ends], res)
    if merged.counts.shape[1] != num_classes:
        raise AssertionError("class axis changed in the merge")
    if all(p.centroids is not None for p, _ in kept):
        slots = np.concatenate([p.centroids for p, _ in kept])[order]
        merged.centroids = _merged_centroids(slots, factor, starts, voxel_of_row)
        merged.centroid_ratio = kept[0][0].centroid_ratio
    return merged


def _merged_centroids(
    slots: np.ndarray, factor: np.ndarray, starts: np.ndarray, voxel_of_row: np.ndarray
) -> np.ndarray:
    """Per voxel the class centroid slots of its rows (`slots`, grouped by voxel from
    `starts`), each row's weights decayed by its `factor` like its counters, folded together
    row after row (tisem/class_centroids.merge_slots)."""
    slots = slots.astype(np.float64, copy=True)
    slots[:, [1, SLOT + 1]] *= factor[:, None]
    rank = np.arange(len(slots)) - starts[voxel_of_row]
    out = slots[starts].copy()
    for r in range(1, int(rank.max()) + 1 if len(rank) else 1):
        rows = np.flatnonzero(rank == r)
        voxels = voxel_of_row[rows]
        out[voxels] = merge_slots(out[voxels], slots[rows])
    return out.astype(np.float32)


def contribution(final: MapSnapshot, seed: MapSnapshot, tau_s: float) -> MapSnapshot:
    """What a run that started from `seed` added: the voxels it updated (new ones, or a later
    t_last than the seed's), with the seed's counters decayed to that time taken out. Voxels
    only the seed had or updated are left out: the map the seed came from holds them."""
    if not len(seed):
        return final
    fk, sk = pack_keys(final.keys), pack_keys(seed.keys)
    pos = np.minimum(np.searchsorted(sk, fk), len(sk) - 1)
    in_seed = sk[pos] == fk
    seed_t = np.where(in_seed, seed.t_last[pos], -np.inf)
    updated = final.t_last > seed_t
    own = take_rows(final, updated)
    rows, had = pos[updated], in_seed[updated]
    counts = own.counts.astype(np.float64)
    factor = decay_factors(own.t_last[had] - seed.t_last[rows[had]], tau_s)
    counts[had] -= factor[:, None] * seed.counts[rows[had]]
    # float32 rounding of the subtraction leaves tiny negatives where a class got nothing new
    np.maximum(counts, 0.0, out=counts)
    out = MapSnapshot(own.keys, counts.astype(np.float32), own.t_last, own.ell_m, own.resolution_m)
    # (the class centroids stay the final map's: where a voxel's points lie, seed included)
    out.centroids, out.centroid_ratio = own.centroids, own.centroid_ratio
    return out


def transform_snapshot(
    snap: MapSnapshot, T_target_source: np.ndarray, tau_s: float = float("inf")
) -> MapSnapshot:
    """The map in another world frame: each voxel centre moved by the rigid transform and
    put in the voxel it lands in (voxels landing together are merged as parts of one map
    would be, with the map's `tau_s`). Exact for translations by whole voxels; a rotation
    resamples the grid. The class centroids (positions inside the voxels) do not follow: a
    moved map answers each voxel's argmax."""
    T = np.asarray(T_target_source, np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"a transform must be 4 x 4, got {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("the transform's rotation is not a rotation")
    if not len(snap):
        return snap
    centres = snap.centers() @ R.T + T[:3, 3]
    keys = np.floor(centres / snap.resolution_m).astype(np.int64)
    moved = MapSnapshot(keys, snap.counts, snap.t_last, snap.ell_m, snap.resolution_m)
    return _fold_duplicates(moved, tau_s)


def _fold_duplicates(snap: MapSnapshot, tau_s: float) -> MapSnapshot:
    """Voxels that share a key summed as `merge_snapshots` would (times kept per voxel)."""
    packed = pack_keys(snap.keys)
    if len(np.unique(packed)) == len(packed):
        return take_rows(snap, MapSnapshot.sort_order(snap.keys))
    # one part per repeat of a key, so that merge_snapshots sees no duplicate inside a part
    order = np.argsort(packed, kind="stable")
    rank = np.empty(len(packed), np.int64)
    sorted_keys = packed[order]
    starts = np.r_[True, sorted_keys[1:] != sorted_keys[:-1]]
    first_of = np.maximum.accumulate(np.where(starts, np.arange(len(order)), 0))
    rank[order] = np.arange(len(order)) - first_of
    parts = [take_rows(snap, rank == r) for r in range(int(rank.max()) + 1)]
    return merge_snapshots(parts, tau_s)


def check_compatible(described: list[tuple[str, float, int]]) -> None:
    """Refuse maps of different resolutions or label spaces: `described` holds (name,
    resolution_m, number of classes) per map."""
    name0, res0, classes0 = described[0]
    for name, res, classes in described[1:]:
        if abs(res - res0) > 1e-9:
            raise ValueError(
                f"{name}: resolution {res} m differs from {name0}'s {res0} m; "
                f"maps of different resolutions cannot be merged"
            )
        if classes != classes0:
            raise ValueError(
                f"{name}: {classes} classes differ from {name0}'s {classes0}; "
                f"maps of different label spaces cannot be merged"
            )
