"""What free space flags of a moving object, spread over the whole object.

Free space finds a mover by the points of it that land in space seen empty (kernels/raycast.py).
That is only part of it: its back is in its own shadow, a slow walker's body overlaps where it
stood a scan ago, and the rays that would show the space ahead of it empty stop a margin short
of their hits. Dynablox (Schmid et al., RA-L 2023) grows such seeds to the cluster of points
they belong to; here, within one scan:

* a cluster is the points of movable classes (tisem.labels.MOVABLE_CLASSES) whose cells of
  `link_m` touch (26-neighbours), and, with `joining` classes (cluster_thin_classes: pole,
  traffic-sign, trunk), the points of those in cells that touch them: the network calls parts
  of a walker pole or trunk, and a voxel it makes so is one rays leave alone
  (spare_thin_static). Joining points count for neither test below: a pole on its own, or one
  a stray ray flags, is never a cluster;
* a cluster holding at least `min_seeds` flagged points, and at least `min_fraction` of its
  points flagged, is dynamic: one stray ray through a parked car does not flag it, nor do the
  dozens a large parked car collects where a mover passed close by (a mover is flagged over
  most of itself: on the synthetic street a parked car's clusters had a median of 2 % of their
  points flagged, a mover's 60-99 %);
* every point in the cells of a dynamic cluster is flagged, whatever its label: the network
  calls parts of a car pole or road, and those parts move with it. Points of static classes
  elsewhere are never flagged by it.

The cells are taken in the sensor frame (a scan's points as they come, no transform: a
transform of every point costs several ms per scan). Dynablox also tracks clusters from scan to
scan; a prototype of that (a cluster next to a recent dynamic one is dynamic too) found next to
none more of the movers on the synthetic street and lost static points (docs/dynamic.md), so
there is none.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

# one int64 per cell, as the store keys its voxels (+-2^20 cells: +-420 km at 0.4 m)
from tisem.store_segments import pack

# the 13 offsets of one half of the 26-neighbourhood: each pair of touching cells once
_HALF = np.array(
    [
        (dx, dy, dz)
        for dx in (-1, 0, 1)
        for dy in (-1, 0, 1)
        for dz in (-1, 0, 1)
        if (dx, dy, dz) > (0, 0, 0)
    ],
    np.int64,
)


def clusters(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The connected groups of touching cells (26-neighbours) among (M, 3) cells: (the distinct
    cells (K, 3) in key order, the group of each (K,), the distinct cell of each input (M,))."""
    keys, of_input = np.unique(pack(cells), return_inverse=True)
    n = len(keys)
    first = np.zeros(n, np.int64)
    first[of_input[::-1]] = np.arange(len(cells))[::-1]
    distinct = cells[first]
    rows, cols = [np.arange(n)], [np.arange(n)]
    for off in _HALF:
        k = pack(distinct + off)
        pos = np.minimum(np.searchsorted(keys, k), n - 1)
        touch = keys[pos] == k
        rows.append(np.flatnonzero(touch))
        cols.append(pos[touch])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(n, n))
    _, group = connected_components(graph, directed=False)
    return distinct, group, of_input


def spread_over_clusters(
    points: np.ndarray,
    labels: np.ndarray,
    dynamic: np.ndarray,
    movable: np.ndarray,
    link_m: float,
    min_seeds: int,
    min_fraction: float = 0.0,
    joining: np.ndarray | None = None,
) -> np.ndarray:
    """(N,) bool: `dynamic`, and every point in the cells of a movable-class cluster that
    holds at least `min_seeds` dynamic points of movable classes, and at least `min_fraction`
    of its movable-class points (see the module's docstring). `points` (N, 3) metres, one
    scan in any one frame; `labels` (N,) class ids; `movable` (C,) bool; `joining` (C,) bool
    or None: the classes whose points join the clusters without counting."""
    of_movable = movable[labels]
    if dynamic[of_movable].sum() < min_seeds:
        return dynamic
    member = of_movable if joining is None else of_movable | joining[labels]
    idx = np.flatnonzero(member)
    counted = of_movable[idx]  # (the movable-class members: what the tests count)
    seeds = dynamic[idx] & counted
    cells = np.floor(points[idx] / link_m).astype(np.int64)
    distinct, group, of_point = clusters(cells)
    point_group = group[of_point]
    n_seeds = np.bincount(point_group, weights=seeds, minlength=group.max() + 1)
    n_points = np.bincount(point_group, weights=counted, minlength=group.max() + 1)
    dynamic_group = (n_seeds >= min_seeds) & (n_seeds >= min_fraction * n_points)
    flagged = distinct[dynamic_group[group]]
    if len(flagged) == 0:
        return dynamic
    # every point in those cells: a box test first spares most points the packing
    inside = _in_box(points, flagged.min(0) * link_m, (flagged.max(0) + 1) * link_m)
    keys = pack(np.floor(points[inside] / link_m).astype(np.int64))
    out = dynamic.copy()
    out[inside[np.isin(keys, pack(flagged))]] = True
    return out


def _in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The indices of the (N, 3) points with lo <= p < hi. One axis over all points, the other
    two over the points it keeps: an (N, 3) comparison reduced along its short axis costs
    several times more (3 ms a scan of 120k points)."""
    x = points[:, 0]
    idx = np.flatnonzero((x >= lo[0]) & (x < hi[0]))
    yz = points[idx, 1:]
    return idx[np.all((yz >= lo[1:]) & (yz < hi[1:]), axis=1)]
