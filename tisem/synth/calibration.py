"""Error statistics of labelled LiDAR scans: how a segmentation network's labels go wrong.

Measured on any SemanticKITTI-layout folder with `labels/` (ground truth) and `predictions/`
(the network), or on synthetic frames, so that the synthetic noise can be checked against the
real network. Everything is kept as counts (mergeable, exact); the properties turn them into
rates. What is measured, over the evaluated points (ground-truth train id != 0, range up to
`max_range_m` — SemanticKITTI's ground truth stops at 50 m):

- the confusion matrix over train ids (rows ground truth, columns prediction);
- errors per (true class, range bin, at a class boundary: `tisem.synth.noise.class_boundary`,
  another true class among the 8 nearest evaluated points within 0.5 m); and how many
  boundary errors take that neighbour's true class ("bleeding" across the edge);
- spatial coherence: for a wrong (or right) point, how often another point at distance d in
  the same scan is wrong (and wrong with the same prediction), for distance bins; and the
  connected error clusters (wrong points with one predicted class, linked within 0.5 m):
  how many wrong points lie in clusters of each size, and of each extent;
- temporal persistence: a point of scan t and the nearest point (within 0.1 m, same true
  class, world frame) of scan t - lag: is the location wrong again, and wrong the same way;
- what a mapper can fix: a point's label replaced by the majority label of the points within
  a radius in its scan and the MAX_LAG scans before it (world frame), right how often;
- what the network says for chosen raw ids, the moving objects (raw 252-259) among them.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from tisem.evaluate import Confusion
from tisem.labels import NUM_CLASSES, raw_to_train
from tisem.synth.noise import class_boundary

RANGE_EDGES_M = (0.0, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 50.0)
DISTANCE_EDGES_M = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0)
CLUSTER_SIZE_EDGES = (1, 2, 10, 100, 1000)  # points; the last bin is open
CLUSTER_EXTENT_EDGES_M = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0)
MAX_LAG = 4
VOTE_RADII_M = (0.2, 0.4, 0.8)
VOTE_SAMPLES = 1000  # points per scan whose neighbourhood vote is taken
# raw ids whose predictions are kept: the movers (252-259) and their static counterparts
MOVING_RAW_IDS = tuple(range(252, 260))
TRACKED_RAW_IDS = (10, 30) + MOVING_RAW_IDS

CLUSTER_LINK_M = 0.5
MATCH_RADIUS_M = 0.1
# points sampled per scan for the distance bins: wrong (and right) centres, and the points
# around them (a uniform sample leaves the rates unbiased)
COHERENCE_CENTRES = 2000
COHERENCE_OTHERS = 20000


@dataclass
class LabelledScan:
    """What the measurement needs of one scan: geometry, raw ground truth, predicted train ids."""

    points: np.ndarray  # (N, 3) float64, sensor frame
    T_world_sensor: np.ndarray  # (4, 4)
    gt_raw: np.ndarray  # (N,) uint32 raw ids (instance bits stripped)
    pred_train: np.ndarray  # (N,) int64


def read_folder(path, first: int = 0, last: int | None = None) -> Iterator[LabelledScan]:
    """The scans of a SemanticKITTI sequence folder with labels/ and predictions/."""
    from tisem.io.semantickitti import SemanticKittiSequence

    seq = SemanticKittiSequence(path, input="predictions", first=first, last=last)
    if not seq.has_ground_truth:
        raise ValueError(f"{seq.sequence_dir}: no labels/ folder (ground truth) to compare with")
    for k in range(len(seq)):
        scan = seq[k]
        # (the reader's: int64 files and train ids as its scans have them)
        gt_raw = seq.label_values(k, "labels", scan.num_points) & np.uint32(0xFFFF)
        keep = np.isfinite(scan.points_sensor).all(axis=1)
        yield LabelledScan(
            scan.points_sensor[keep].astype(np.float64),
            scan.T_world_sensor,
            gt_raw[keep],
            scan.labels[keep].astype(np.int64),
        )


def from_synth_frames(frames: Iterable) -> Iterator[LabelledScan]:
    """LabelledScans of synthetic frames (`tisem.synth.SynthFrame`), without writing files."""
    for f in frames:
        yield LabelledScan(
            f.points.astype(np.float64),
            f.T_world_lidar,
            f.gt_raw,
            raw_to_train(f.pred_raw)[0].astype(np.int64),
        )


def _zeros(*shape) -> np.ndarray:
    return np.zeros(shape, dtype=np.int64)


@dataclass
class ErrorStatistics:
    """Counts of a network's errors over some scans (see the module docstring)."""

    max_range_m: float = RANGE_EDGES_M[-1]
    scans: int = 0
    confusion: np.ndarray = field(default_factory=lambda: _zeros(NUM_CLASSES, NUM_CLASSES))
    # (class, range bin, at boundary 0/1): evaluated points and wrong ones
    cell_points: np.ndarray = field(
        default_factory=lambda: _zeros(NUM_CLASSES, len(RANGE_EDGES_M) - 1, 2)
    )
    cell_errors: np.ndarray = field(
        default_factory=lambda: _zeros(NUM_CLASSES, len(RANGE_EDGES_M) - 1, 2)
    )
    bleed_errors: int = 0  # boundary errors that took a neighbour's true class
    # neighbour pairs per distance bin, from wrong centres: all, wrong, wrong the same way;
    # from right centres: all, wrong
    pairs: np.ndarray = field(default_factory=lambda: _zeros(5, len(DISTANCE_EDGES_M) - 1))
    cluster_points_by_size: np.ndarray = field(
        default_factory=lambda: _zeros(len(CLUSTER_SIZE_EDGES))
    )
    cluster_points_by_extent: np.ndarray = field(
        default_factory=lambda: _zeros(len(CLUSTER_EXTENT_EDGES_M))
    )
    # per lag 1..MAX_LAG: matched points wrong before, of them wrong now, of those with the
    # same label; matched points right before, of them wrong now
    persistence: np.ndarray = field(default_factory=lambda: _zeros(MAX_LAG, 5))
    raw_predictions: dict = field(
        default_factory=lambda: {r: _zeros(NUM_CLASSES) for r in TRACKED_RAW_IDS}
    )
    # sampled points: how many, right as labelled, right after the vote at each radius
    vote: np.ndarray = field(default_factory=lambda: _zeros(2 + len(VOTE_RADII_M)))

    def merge(self, other: ErrorStatistics) -> ErrorStatistics:
        """Add another measurement's counts (of other scans) into these. Returns self."""
        for name, value in vars(other).items():
            if name == "raw_predictions":
                for raw, counts in value.items():
                    self.raw_predictions[raw] = self.raw_predictions[raw] + counts
            elif name != "max_range_m":
                setattr(self, name, getattr(self, name) + value)
        return self

    # ------------------------------------------------------------------ rates
    @property
    def points(self) -> int:
        return int(self.confusion.sum())

    def metrics(self) -> dict:
        """`tisem.evaluate.Confusion.metrics()` of the predictions (accuracy, mIoU, IoUs)."""
        c = Confusion()
        flat = np.repeat(np.arange(NUM_CLASSES**2), self.confusion.ravel())
        return c.add(flat // NUM_CLASSES, flat % NUM_CLASSES).metrics()

    def row_normalised(self) -> np.ndarray:
        """(C, C) P(prediction | true class); rows without points are zero."""
        n = self.confusion.sum(axis=1, keepdims=True)
        return np.divide(self.confusion, n, out=np.zeros(self.confusion.shape), where=n > 0)

    def error_rate_by_range(self) -> np.ndarray:
        return _ratio(self.cell_errors.sum(axis=(0, 2)), self.cell_points.sum(axis=(0, 2)))

    def class_error_rate(self) -> np.ndarray:
        """(C,) P(wrong | true class), NaN for absent classes."""
        return _ratio(self.cell_errors.sum(axis=(1, 2)), self.cell_points.sum(axis=(1, 2)))

    def boundary(self) -> dict:
        """Share of points at a class boundary, error rates there and inside, and how many
        boundary errors take a neighbour's class."""
        n, w = self.cell_points.sum(axis=(0, 1)), self.cell_errors.sum(axis=(0, 1))
        return {
            "share": _ratio(n[1], n.sum()),
            "error_at_boundary": _ratio(w[1], n[1]),
            "error_inside": _ratio(w[0], n[0]),
            "bleed": _ratio(self.bleed_errors, w[1]),
        }

    def coherence(self) -> dict:
        """Per distance bin: P(other point wrong | point wrong), P(... wrong the same way |
        point wrong), P(other point wrong | point right)."""
        p = self.pairs
        return {
            "wrong_given_wrong": _ratio(p[1], p[0]),
            "same_given_wrong": _ratio(p[2], p[0]),
            "wrong_given_right": _ratio(p[4], p[3]),
        }

    def cluster_shares(self) -> tuple[np.ndarray, np.ndarray]:
        """Shares of wrong points in clusters by size bin and by extent bin."""
        return (
            _ratio(self.cluster_points_by_size, self.cluster_points_by_size.sum()),
            _ratio(self.cluster_points_by_extent, self.cluster_points_by_extent.sum()),
        )

    def persistence_rates(self) -> dict:
        """Per lag: P(wrong | wrong before), P(same label | wrong both times),
        P(wrong | right before)."""
        q = self.persistence.T
        return {
            "wrong_given_wrong": _ratio(q[1], q[0]),
            "same_label": _ratio(q[2], q[1]),
            "wrong_given_right": _ratio(q[4], q[3]),
        }

    def vote_accuracy(self) -> tuple[float, np.ndarray]:
        """Accuracy of the sampled points as labelled, and after the vote at each radius."""
        return float(_ratio(self.vote[1], self.vote[0])), _ratio(self.vote[2:], self.vote[0])

    def raw_prediction_shares(self, raw_id: int) -> np.ndarray:
        counts = self.raw_predictions[raw_id]
        return _ratio(counts, counts.sum())


def _ratio(a, b):
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return np.divide(a, b, out=np.full(np.broadcast(a, b).shape, np.nan), where=b > 0)


# ---------------------------------------------------------------------------- measurement


@dataclass
class _Evaluated:
    """The evaluated points of one scan, with a tree over them."""

    points: np.ndarray
    world: np.ndarray
    gt: np.ndarray
    pred: np.ndarray
    tree_world: cKDTree

    @property
    def wrong(self) -> np.ndarray:
        return self.pred != self.gt


def measure(
    scans: Iterable[LabelledScan], max_range_m: float = RANGE_EDGES_M[-1], seed: int = 0
) -> ErrorStatistics:
    """Error statistics of the scans, in order (consecutive scans give the persistence)."""
    stats = ErrorStatistics(max_range_m=max_range_m)
    rng = np.random.default_rng(seed)
    previous: deque[_Evaluated] = deque(maxlen=MAX_LAG)
    for scan in scans:
        gt, _ = raw_to_train(scan.gt_raw)
        range_m = np.linalg.norm(scan.points, axis=1)
        keep = (gt > 0) & (range_m <= max_range_m)
        for raw in TRACKED_RAW_IDS:
            stats.raw_predictions[raw] += np.bincount(
                scan.pred_train[keep & (scan.gt_raw == raw)], minlength=NUM_CLASSES
            )
        T = scan.T_world_sensor
        points = scan.points[keep]
        world = points @ T[:3, :3].T + T[:3, 3]
        now = _Evaluated(
            points, world, gt[keep].astype(np.int64), scan.pred_train[keep], cKDTree(world)
        )
        stats.confusion += np.bincount(
            now.gt * NUM_CLASSES + now.pred, minlength=NUM_CLASSES**2
        ).reshape(NUM_CLASSES, -1)
        _count_cells(stats, now, range_m[keep])
        _count_pairs(stats, now, rng)
        _count_clusters(stats, now)
        for lag, before in enumerate(reversed(previous), start=1):
            _count_persistence(stats, before, now, lag)
        _count_votes(stats, now, list(previous), rng)
        previous.append(now)
        stats.scans += 1
    return stats


def _count_cells(stats: ErrorStatistics, s: _Evaluated, range_m: np.ndarray) -> None:
    """Errors per (class, range bin, boundary), and boundary errors that bleed."""
    neighbour = class_boundary(s.world, s.gt, s.tree_world)
    at_boundary = neighbour >= 0
    bins = np.clip(
        np.searchsorted(RANGE_EDGES_M, range_m, side="right") - 1, 0, len(RANGE_EDGES_M) - 2
    )
    shape = stats.cell_points.shape
    cell = np.ravel_multi_index((s.gt, bins, at_boundary.astype(np.int64)), shape)
    size = int(np.prod(shape))
    stats.cell_points += np.bincount(cell, minlength=size).reshape(shape)
    stats.cell_errors += np.bincount(cell[s.wrong], minlength=size).reshape(shape)
    stats.bleed_errors += int(np.count_nonzero(s.wrong & (s.pred == neighbour)))


def _count_pairs(stats: ErrorStatistics, s: _Evaluated, rng: np.random.Generator) -> None:
    """Neighbour pairs by distance bin between sampled wrong (and right) centres and a sample
    of the scan's points (dual-tree counts; a tiny first radius drops a point's pair with
    itself)."""
    radii = np.array([1e-9, *DISTANCE_EDGES_M[1:]])
    wrong = s.wrong
    centre_wrong = _sample(np.flatnonzero(wrong), COHERENCE_CENTRES, rng)
    centre_right = _sample(np.flatnonzero(~wrong), COHERENCE_CENTRES, rng)
    others = _sample(np.arange(len(wrong)), COHERENCE_OTHERS, rng)
    others_wrong = others[wrong[others]]

    def pairs(centres: np.ndarray, targets: np.ndarray) -> np.ndarray:
        if not len(centres) or not len(targets):
            return np.zeros(len(radii) - 1, dtype=np.int64)
        counts = cKDTree(s.points[centres]).count_neighbors(cKDTree(s.points[targets]), radii)
        return np.diff(counts)

    same = sum(
        (
            pairs(centre_wrong[s.pred[centre_wrong] == c], others_wrong[s.pred[others_wrong] == c])
            for c in np.unique(s.pred[centre_wrong])
        ),
        np.zeros(len(radii) - 1, np.int64),
    )
    stats.pairs += np.stack(
        [
            pairs(centre_wrong, others),
            pairs(centre_wrong, others_wrong),
            same,
            pairs(centre_right, others),
            pairs(centre_right, others_wrong),
        ]
    )


def _sample(idx: np.ndarray, at_most: int, rng: np.random.Generator) -> np.ndarray:
    return np.sort(rng.choice(idx, at_most, replace=False)) if len(idx) > at_most else idx


def _count_clusters(stats: ErrorStatistics, s: _Evaluated) -> None:
    """Connected components of wrong points with one predicted class, linked within
    CLUSTER_LINK_M; each wrong point counted in its cluster's size and extent bins."""
    wrong = np.flatnonzero(s.wrong)
    if not len(wrong):
        return
    pts, pred = s.points[wrong], s.pred[wrong]
    link = cKDTree(pts).query_pairs(CLUSTER_LINK_M, output_type="ndarray")
    link = link[pred[link[:, 0]] == pred[link[:, 1]]]
    graph = coo_matrix((np.ones(len(link)), (link[:, 0], link[:, 1])), shape=(len(pts),) * 2)
    _, cluster = connected_components(graph, directed=False)
    size = np.bincount(cluster)[cluster]
    lo = np.full((cluster.max() + 1, 3), np.inf)
    hi = np.full((cluster.max() + 1, 3), -np.inf)
    np.minimum.at(lo, cluster, pts)
    np.maximum.at(hi, cluster, pts)
    extent = np.linalg.norm(hi - lo, axis=1)[cluster]
    stats.cluster_points_by_size += np.bincount(
        np.searchsorted(CLUSTER_SIZE_EDGES, size, side="right") - 1,
        minlength=len(CLUSTER_SIZE_EDGES),
    )
    stats.cluster_points_by_extent += np.bincount(
        np.searchsorted(CLUSTER_EXTENT_EDGES_M, extent, side="right") - 1,
        minlength=len(CLUSTER_EXTENT_EDGES_M),
    )


def _count_persistence(
    stats: ErrorStatistics, before: _Evaluated, now: _Evaluated, lag: int
) -> None:
    """Locations seen in both scans (nearest point within MATCH_RADIUS_M, same true class)."""
    dist, idx = before.tree_world.query(now.world, distance_upper_bound=MATCH_RADIUS_M)
    found = np.isfinite(dist)
    idx = np.where(found, idx, 0)
    matched = found & (before.gt[idx] == now.gt)
    was_wrong = before.wrong[idx]
    wrong_now = now.wrong
    same = before.pred[idx] == now.pred
    a, b = matched & was_wrong, matched & ~was_wrong
    stats.persistence[lag - 1] += [
        a.sum(),
        (a & wrong_now).sum(),
        (a & wrong_now & same).sum(),
        b.sum(),
        (b & wrong_now).sum(),
    ]


def _count_votes(
    stats: ErrorStatistics, now: _Evaluated, before: list[_Evaluated], rng: np.random.Generator
) -> None:
    """Majority vote of the labels around sampled points of `now`, over it and `before`."""
    window = [now, *before]
    world = np.concatenate([s.world for s in window])
    labels = np.concatenate([s.pred for s in window])
    tree = now.tree_world if not before else cKDTree(world)
    sample = _sample(np.arange(len(now.gt)), VOTE_SAMPLES, rng)
    lists = tree.query_ball_point(now.world[sample], VOTE_RADII_M[-1])
    owner = np.repeat(np.arange(len(sample)), [len(n) for n in lists])
    neighbour = np.concatenate([np.asarray(n, dtype=np.int64) for n in lists])
    dist = np.linalg.norm(world[neighbour] - now.world[sample][owner], axis=1)
    right = [len(sample), int(np.count_nonzero(~now.wrong[sample]))]
    for radius in VOTE_RADII_M:
        near = dist <= radius
        votes = np.bincount(
            owner[near] * NUM_CLASSES + labels[neighbour[near]], minlength=len(sample) * NUM_CLASSES
        ).reshape(len(sample), -1)
        right.append(int(np.count_nonzero(votes.argmax(axis=1) == now.gt[sample])))
    stats.vote += right
