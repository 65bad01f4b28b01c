"""The free-space DDA (kernels/raycast.py) against an exact numpy reference: every voxel a ray
crosses, in order, none skipped, none extra; rays along axes, through voxel edges and corners,
and rays shorter than their margin."""

import numpy as np
import pytest
from tisem.kernels import raycast

MAX_VOXELS = 2048


def reference_pieces(o, e, inv_res, margin_m, margin_fraction):
    """The pieces the faces cut the segment from o to a margin before e into, in order: each
    piece's voxel (its midpoint's) and its length as a fraction of the ray."""
    o = np.asarray(o, np.float64)
    e = np.asarray(e, np.float64)
    length = np.linalg.norm(e - o)
    t_stop = (length - max(margin_m, margin_fraction * length)) / length if length else 0.0
    if t_stop <= 0:
        return [], np.zeros(0)
    # voxel units as the kernel scales them (float32), then float64
    inv32 = np.float32(inv_res)
    ov = (np.float32(o) * inv32).astype(np.float64)
    dv = (np.float32(e) * inv32).astype(np.float64) - ov
    cuts = [0.0, t_stop]
    for a in range(3):
        if dv[a] == 0:
            continue
        lo, hi = sorted((ov[a], ov[a] + dv[a]))
        faces = np.arange(np.floor(lo) + 1, np.floor(hi) + 1)
        cuts += list((faces - ov[a]) / dv[a])
    cuts = np.unique(np.clip(cuts, 0.0, t_stop))
    mids = (cuts[:-1] + cuts[1:]) / 2
    return [tuple(v) for v in np.floor(ov + mids[:, None] * dv).astype(int)], np.diff(cuts)


def reference_voxels(o, e, inv_res, margin_m, margin_fraction):
    """Exactly the voxels a ray crosses (exact ties only: for rays through exact corners)."""
    voxels, pieces = reference_pieces(o, e, inv_res, margin_m, margin_fraction)
    return [v for v, p in zip(voxels, pieces) if p > 0]


def kernel_voxels(origins, ends, inv_res, margin_m, margin_fraction):
    origins = np.ascontiguousarray(origins, np.float32)
    ends = np.ascontiguousarray(ends, np.float32)
    out = np.zeros((len(origins), MAX_VOXELS, 3), np.int32)
    count = np.zeros(len(origins), np.int32)
    raycast.trace_rays(origins, ends, inv_res, margin_m, margin_fraction, out, count)
    assert count.max() <= MAX_VOXELS
    return [[tuple(v) for v in out[r, : count[r]]] for r in range(len(origins))]


def check_rays(origins, ends, inv_res, margin_m=0.0, margin_fraction=0.0):
    """The kernel's voxels are the reference's: in order, each once; a voxel the ray passes
    within TIE_T of an edge or corner of (so only touches, up to rounding) may go either way."""
    got = kernel_voxels(origins, ends, inv_res, margin_m, margin_fraction)
    for r, voxels in enumerate(got):
        # the reference sees the float32 values the kernel sees
        want, pieces = reference_pieces(
            np.float32(origins[r]), np.float32(ends[r]), inv_res, margin_m, margin_fraction
        )
        crossed = [v for v, p in zip(want, pieces) if p > 10 * raycast.TIE_T]
        touched = [v for v, p in zip(want, pieces) if p > 0]
        where = f"ray {r}: {origins[r]} -> {ends[r]}"
        assert len(set(voxels)) == len(voxels), where
        assert [v for v in voxels if v in set(crossed)] == crossed, where + ": skipped"
        assert set(voxels) <= set(touched), where + ": extra"
    return got


@pytest.mark.slow  # (400 long rays, each checked against the reference in Python)
def test_random_rays_cross_exactly_the_reference_voxels(taichi_cpu):
    rng = np.random.default_rng(16)
    origins = rng.uniform(-3, 3, (400, 3))
    ends = origins + rng.normal(0, 1, (400, 3)) * rng.uniform(0.1, 25, (400, 1))
    got = check_rays(origins, ends, 1 / 0.2, margin_m=0.3, margin_fraction=0.1)
    assert sum(map(len, got)) > 10_000  # long rays: the test sees many steps
    for voxels in got:  # each step to a face neighbour or across a tie
        steps = np.abs(np.diff(np.array(voxels).reshape(-1, 3), axis=0))
        assert (steps <= 1).all()


@pytest.mark.parametrize("direction", [(1, 0, 0), (0, -1, 0), (0, 0, 1), (-1, 0, 0)])
def test_rays_along_axes(taichi_cpu, direction):
    o = np.array([[0.1, 0.1, 0.1], [0.2, 0.4, -0.6]])  # inside a voxel, and on voxel faces
    e = o + 7.3 * np.array(direction, float)
    got = check_rays(o, e, 1 / 0.2)
    a = int(np.flatnonzero(direction)[0])
    for voxels in got:
        assert len(voxels) == len(set(voxels))
        assert all(v[b] == voxels[0][b] for v in voxels for b in range(3) if b != a)


def test_rays_through_edges_and_corners_step_every_axis_at_once(taichi_cpu):
    res = 0.25  # exact in float32: the ties are exact ties
    o = np.full((3, 3), 0.125)  # a voxel centre
    e = o + res * np.array([[6, 6, 6], [-6, 6, -6], [4, 4, 1]])
    got = check_rays(o, e, 1 / res)
    assert got[0] == [(i, i, i) for i in range(7)]  # corners: the diagonal alone
    assert got[1] == [(-i, i, -i) for i in range(7)]
    # edges along z: x and y step together, z once on its own
    assert got[2] == [(0, 0, 0), (1, 1, 0), (2, 2, 0), (2, 2, 1), (3, 3, 1), (4, 4, 1)]


def test_margin_stops_rays_before_the_hit(taichi_cpu):
    o = np.zeros((3, 3)) + 0.05
    e = o + np.array([[10.0, 0, 0], [0.4, 0, 0], [0, 0, 0]])
    got = check_rays(o, e, 1 / 0.2, margin_m=0.5, margin_fraction=0.1)
    assert got[0][-1] == (45, 0, 0)  # stops 1 m (10 %) before x = 10.05
    assert got[1] == [] and got[2] == []  # shorter than the margin; no length at all
