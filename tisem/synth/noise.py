""" "Network" predictions: ground truth corrupted the way a real LiDAR segmentation network errs.

What goes wrong comes from a `NetworkProfile` (by default the real network's on SemanticKITTI
08 frames 0-4, `tisem.synth.profile`): P(wrong) per true class and range, raised or lowered at
class boundaries, what each class is taken for, how moving objects are labelled. Where the
errors fall follows the real network's structure (`benchmarks/noise_calibration.py` compares
the two):

- coherent in space: a point is wrong where a latent Gaussian field lies below the quantile
  of its error probability, so errors come as patches, not salt. The latent mixes a fine
  field (0.7 m), a coarse one drawn per true class (6 m: whole stretches of a class wrong,
  cut at the class's edges, which neighbourhood votes cannot repair) and per-point noise
  (isolated errors); a third, smooth field picks the wrong label, so a patch is mostly one
  wrong class;
- persistent in time: the fields live in world coordinates and drift slowly (a new field
  every `drift_scans` scans, blended in), so a location that is wrong in one scan is likely
  wrong in the next few (averaging consecutive scans cannot remove most errors), while a
  revisit much later sees fresh ones;
- at a class boundary a wrong point often takes its neighbour's class (bleeding).
Every field is a function of (seed, world position, scan index, class), so a scan
regenerates alone. A prediction is 0 only where the ground truth is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import ndtr, ndtri

from tisem.synth.profile import NetworkProfile, kitti08_profile
from tisem.synth.scene import PERSON, PERSON_INSTANCE

MOVING_PERSON = 254  # SemanticKITTI's raw id of a moving person

BOUNDARY_NEIGHBOURS = 8
BOUNDARY_RADIUS_M = 0.5


def class_boundary(
    points: np.ndarray, gt_train: np.ndarray, tree: cKDTree | None = None
) -> np.ndarray:
    """(N,) class of another-class neighbour per point, -1 inside a class: among the point's
    BOUNDARY_NEIGHBOURS nearest points within BOUNDARY_RADIUS_M, the nearest with another
    class. The one definition of "at a class boundary" for the noise and its measurement.

    Only points with another class in the voxels around theirs can be at a boundary, so only
    those (a small share) are queried; `tree` (over `points`) saves building one."""
    gt_train = np.asarray(gt_train, dtype=np.int64)
    neighbour = np.full(len(points), -1, dtype=np.int64)
    candidates = np.flatnonzero(_other_class_nearby(points, gt_train))
    if not len(candidates):
        return neighbour
    tree = cKDTree(points) if tree is None else tree
    dist, idx = tree.query(
        points[candidates], k=BOUNDARY_NEIGHBOURS + 1, distance_upper_bound=BOUNDARY_RADIUS_M
    )
    dist, idx = dist[:, 1:], idx[:, 1:]  # the point itself comes first
    valid = np.isfinite(dist)
    other = np.where(valid, gt_train[np.where(valid, idx, 0)], -1)
    other[other == gt_train[candidates, None]] = -1
    neighbour[candidates] = other[np.arange(len(other)), np.argmax(other >= 0, axis=1)]
    return neighbour


def _other_class_nearby(points: np.ndarray, gt_train: np.ndarray) -> np.ndarray:
    """(N,) whether the 3 x 3 x 3 voxels of BOUNDARY_RADIUS_M around a point's voxel hold
    another class: true for every point with another class within the radius."""
    cell = np.floor(np.asarray(points) / BOUNDARY_RADIUS_M).astype(np.int64)
    keys, which = np.unique(_pack(cell), return_inverse=True)
    classes = np.zeros(len(keys), dtype=np.int64)  # bit c: class c in the voxel
    np.bitwise_or.at(classes, which.ravel(), np.left_shift(1, gt_train))
    cells, _ = _unpack(keys)
    around = classes.copy()
    for offset in np.argwhere(np.ones((3, 3, 3))) - 1:
        if not offset.any():
            continue
        wanted = _pack(cells + offset)
        at = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
        found = keys[at] == wanted
        around[found] |= classes[at[found]]
    return (around[which.ravel()] & ~np.left_shift(1, gt_train)) != 0


_AXIS_BITS, _LAYER_BITS = 19, 5


def _pack(cells: np.ndarray, layer: np.ndarray | None = None) -> np.ndarray:
    """One int64 per integer cell (n, 3) and layer (0..31): 19 bits per axis (cells within
    +-2^18 of the origin), 5 for the layer."""
    b = cells + (1 << (_AXIS_BITS - 1))
    packed = (b[:, 0] << (2 * _AXIS_BITS)) | (b[:, 1] << _AXIS_BITS) | b[:, 2]
    return packed << _LAYER_BITS | (0 if layer is None else layer)


def _unpack(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cells (n, 3), layers (n,)) of packed keys."""
    mask = (1 << _AXIS_BITS) - 1
    b = keys >> _LAYER_BITS
    cells = np.stack([b >> (2 * _AXIS_BITS), (b >> _AXIS_BITS) & mask, b & mask], axis=1)
    return cells - (1 << (_AXIS_BITS - 1)), keys & ((1 << _LAYER_BITS) - 1)


def mover_raw_ids(gt_raw: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """(N,) raw id of the moving object a point is on (252-259), 0 for static points. The
    synthetic person walks but keeps raw id 30: it counts as a moving person (254)."""
    moving = np.where((gt_raw >= 252) & (gt_raw <= 259), gt_raw, 0).astype(np.int64)
    moving[(gt_raw == PERSON) & (instance == PERSON_INSTANCE)] = MOVING_PERSON
    return moving


# ----------------------------------------------------------------------------- fields


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser: a uint64 hash with every input bit reaching every output bit."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def _lattice_normal(cells: np.ndarray, layer: np.ndarray, key: int) -> np.ndarray:
    """A standard normal per integer lattice cell (n, 3) and layer (n,), a pure function of
    (cells, layer, key): the packed cell (distinct for distinct cells) hashed with the key."""
    with np.errstate(over="ignore"):
        h = _mix(_mix(_pack(cells, layer).view(np.uint64) + np.uint64(key)))
    return ndtri(((h >> np.uint64(11)).astype(np.float64) + 0.5) / 2.0**53)


# corner k of a lattice cell: offsets (k >> 2, k >> 1, k) & 1 along x, y, z — the order of
# a (2, 2, 2) array flattened
_CORNERS = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)])


def gaussian_fields(
    points: np.ndarray, spacing_m: float, keys, layer: np.ndarray | None = None
) -> np.ndarray:
    """(len(keys), n) independent smooth random fields at the points, one per key, each with
    an exact N(0, 1) marginal everywhere; points of different `layer` (n,) ints in [0, 32)
    see independent fields (a field per class: smooth within a class, cut at its edges).

    Value noise: normals on a lattice of `spacing_m`, blended with smoothstep weights w and
    divided by sqrt(sum w^2), which makes the blend's variance 1 between lattice points too;
    the correlation falls to ~0 over one spacing. The weights are shared by the keys, and the
    normals drawn once per lattice cell (and layer) the points touch."""
    x = np.asarray(points, dtype=np.float64) / spacing_m
    base = np.floor(x)
    upper = x - base
    upper = upper * upper * (3.0 - 2.0 * upper)
    axis = np.stack([1.0 - upper, upper], axis=-1)  # (n, 3, 2)
    # the weights are a product over the axes, and so is sum w^2
    axis /= np.sqrt((axis * axis).sum(axis=2, keepdims=True))
    w = (axis[:, 0, :, None, None] * axis[:, 1, None, :, None] * axis[:, 2, None, None, :]).reshape(
        len(x), 8
    )
    packed, which = np.unique(_pack(base.astype(np.int64), layer), return_inverse=True)
    cells, layers = _unpack(packed)
    corners = (cells[:, None, :] + _CORNERS).reshape(-1, 3)
    corner_layers = np.repeat(layers, len(_CORNERS))
    out = np.empty((len(keys), len(x)))
    for k, key in enumerate(keys):
        values = _lattice_normal(corners, corner_layers, key).reshape(len(cells), 8)
        out[k] = np.einsum("ij,ij->i", w, values[which.ravel()])
    return out


def drifting_field(
    points: np.ndarray,
    spacing_m: float,
    key: int,
    scan_index: int,
    drift_scans: float,
    layer: np.ndarray | None = None,
) -> np.ndarray:
    """A smooth N(0, 1) field that changes over time: epoch k = scan_index // drift_scans has
    its own field F_k, and between epochs the field turns from F_k to F_k+1 as
    cos(a) F_k + sin(a) F_k+1 (still N(0, 1)); scans a lag L apart correlate by about
    cos(pi L / (2 drift_scans)), and not at all from 2 drift_scans on."""
    phase = scan_index / drift_scans
    epoch = int(np.floor(phase))
    angle = 0.5 * np.pi * (phase - epoch)
    now, then = gaussian_fields(points, spacing_m, (_key(key, epoch), _key(key, epoch + 1)), layer)
    return np.cos(angle) * now + np.sin(angle) * then


def _key(*parts: int) -> int:
    """One 64-bit key of several integers (a field's seed, purpose and epoch)."""
    h = np.zeros(1, dtype=np.uint64)
    with np.errstate(over="ignore"):
        for p in parts:
            h = _mix(h + np.uint64(p & 0xFFFFFFFFFFFFFFFF))
    return int(h[0])


# ----------------------------------------------------------------------------- the model


@dataclass(frozen=True)
class NoiseModel:
    """Calibrated to the real network (see the module docstring and `tisem.synth.profile`).

    The field parameters are set so that the synthetic street's coherence and persistence
    statistics (`benchmarks/noise_calibration.py`) match the real frames'."""

    profile: NetworkProfile = field(default_factory=kitti08_profile)
    patch_m: float = 0.7  # lattice spacing of the error field
    region_patch_m: float = 6.0  # ... of its per-class part (whole regions wrong)
    region_share: float = 0.5  # variance share of the per-class part
    label_patch_m: float = 4.0  # lattice spacing of the field that picks wrong labels
    drift_scans: float = 30.0  # the fields renew over this many scans
    white_share: float = 0.1  # variance share of per-point noise in the error latent
    bleed_prob: float = 0.7  # a wrong point at a boundary takes the neighbour's class

    def apply(
        self,
        gt_train: np.ndarray,
        range_m: np.ndarray,
        points_world: np.ndarray,
        mover_raw: np.ndarray,
        seed: int,
        scan_index: int,
        rng: np.random.Generator,
    ) -> np.ndarray:
        """Predicted train ids (int64) for one scan's points: their true classes, the points'
        ranges and world positions, the moving raw id of each (`mover_raw_ids`), the
        sequence's seed, the scan's index and its random stream."""
        gt_train = np.asarray(gt_train, dtype=np.int64)
        rows = self.profile.row_of(gt_train, mover_raw)
        neighbour = class_boundary(points_world, gt_train)
        at_boundary = neighbour >= 0
        p_wrong = self.profile.error_probability(rows, range_m, at_boundary)

        fine = self._latent(points_world, self.patch_m, _key(seed, 1), scan_index)
        region = self._latent(
            points_world, self.region_patch_m, _key(seed, 3), scan_index, gt_train
        )
        latent = (
            np.sqrt(1.0 - self.white_share - self.region_share) * fine
            + np.sqrt(self.region_share) * region
            + np.sqrt(self.white_share) * rng.standard_normal(len(gt_train))
        )
        wrong = (latent < ndtri(p_wrong)) & (gt_train > 0)
        pred = gt_train.copy()
        # the label field, at the wrong points only (a field's value does not depend on
        # which other points it is evaluated at)
        u = ndtr(self._latent(points_world[wrong], self.label_patch_m, _key(seed, 2), scan_index))
        pred[wrong] = self.profile.wrong_label(rows[wrong], u)
        bleed = wrong & at_boundary & (mover_raw == 0) & (rng.random(len(pred)) < self.bleed_prob)
        pred[bleed] = neighbour[bleed]
        return pred

    def _latent(
        self,
        points: np.ndarray,
        spacing_m: float,
        key: int,
        scan_index: int,
        layer: np.ndarray | None = None,
    ) -> np.ndarray:
        return drifting_field(points, spacing_m, key, scan_index, self.drift_scans, layer)
