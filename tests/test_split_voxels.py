"""The split-voxel statistic (tisem/synth/split_voxels.py) on scenes with known answers."""

from __future__ import annotations

import numpy as np

from tisem.synth.split_voxels import SplitVoxels

ROAD, SIDEWALK = 9, 11


def one_voxel(rng, n_road, n_side):
    """Road points on the low-x half of the voxel [0, 0.2)^3, sidewalk on the high-x half."""
    road = rng.uniform([0.01, 0.01, 0.01], [0.09, 0.19, 0.19], (n_road, 3))
    side = rng.uniform([0.11, 0.01, 0.01], [0.19, 0.19, 0.19], (n_side, 3))
    return np.concatenate([road, side]), np.r_[np.full(n_road, ROAD), np.full(n_side, SIDEWALK)]


def test_labels_that_follow_the_boundary_are_right_by_the_nearer_class():
    pts, gt = one_voxel(np.random.default_rng(0), 6, 4)
    s = SplitVoxels()
    s.add(pts, gt, gt.copy())
    assert (s.points, s.leading_right, s.nearer_right) == (10, 6, 10)


def test_a_second_label_too_small_or_scattered_does_not_help():
    """3 of 10 is below half of 7: no split voxel; labels scattered at random through the
    voxel (the ground truth one class) leave the nearer class no better than the leading one."""
    rng = np.random.default_rng(1)
    pts, gt = one_voxel(rng, 7, 3)
    s = SplitVoxels()
    s.add(pts, gt, gt.copy())
    assert s.points == 0
    pts = rng.uniform(0.01, 0.19, (400, 3)) + np.repeat(np.arange(40), 10)[:, None] * 0.2
    pred = np.where(rng.random(400) < 0.45, SIDEWALK, ROAD)
    s = SplitVoxels()
    s.add(pts, np.full(400, ROAD), pred)
    leading, nearer = s.shares()
    assert s.points > 100 and nearer < leading
