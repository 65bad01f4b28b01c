"""Steps 6-8: the compact-support sparse kernel, the Bayesian kernel update and its fusion.

Gather form: each live map voxel v near the scan sums k(v, p) * h(p) over the training points
within its own kernel length L(v), then folds the sum into its counters. The work per voxel
grows with L(v)^3, so low-entropy voxels (short kernels) are cheap: the adaptive kernel pays
only where the map is uncertain. No atomics: each voxel is written by one thread.

Training points are sorted by leaf block (kernels/training.py). A receiving block first lists
the non-empty training blocks within reach of any of its voxels (one sparse lookup per block,
shared by its up to 64 voxels); each voxel then visits only listed blocks its sphere touches.
"""
import math

import taichi as ti

from kernels.fusion import fuse_voxel
from kernels.layout import LEAF

# Evidence below this is float noise at the kernel's edge (g -> 0 as d -> L), not an update:
# counting it would reset t_last and, with alpha = 0, wipe the voxel's history.
MIN_UPDATE = 1e-6
# Most neighbour blocks a receiving block can list: (2 * 2 + 1)^3 for a reach of two blocks.
MAX_REACH_BLK = 2
MAX_LIST = (2 * MAX_REACH_BLK + 2) ** 3


@ti.func
def sparse_kernel(r):
    """Melkumyan-Ramos g(r) for r = d / L in [0, 1): 1 at r = 0, 0 with zero slope at r = 1."""
    two_pi_r = 2.0 * math.pi * r
    g = (2.0 + ti.cos(two_pi_r)) / 3.0 * (1.0 - r) + ti.sin(two_pi_r) / (2.0 * math.pi)
    return ti.max(g, 0.0)    # the two terms cancel near r = 1: never let rounding go negative


@ti.kernel
def mark_receivers(m: ti.template(), stamp: ti.i32, reach_blk: ti.i32):
    """Stamp every live map block within `reach_blk` blocks of a block holding training points."""
    for B in ti.grouped(m.s_bcount):
        if m.s_bcount[B] > 0:
            for dx, dy, dz in ti.ndrange((-reach_blk, reach_blk + 1), (-reach_blk, reach_blk + 1),
                                         (-reach_blk, reach_blk + 1)):
                nb = m.wrap_blk(B + ti.Vector([dx, dy, dz]))
                if ti.is_active(m.blk, nb):
                    m.blk_stamp[nb] = stamp


@ti.func
def box_distance2(p, lo, hi):
    """Squared distance from point p to the axis-aligned box [lo, hi]."""
    d = ti.max(lo - p, 0.0) + ti.max(p - hi, 0.0)
    return d.dot(d)


@ti.kernel
def gather_update(m: ti.template(), center: ti.types.vector(3, ti.i32), stamp: ti.i32,
                  t: ti.f32, inv_tau: ti.f32, resolution: ti.f32, sigma0: ti.f32,
                  xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),     # (K, 3) training points
                  hist: ti.types.ndarray(dtype=ti.f32, ndim=2),    # (K, C) block-sorted
                  classes: ti.types.ndarray(dtype=ti.i32, ndim=1)):  # (K,) bit c: hist[:, c] > 0
    blk_m = LEAF * resolution
    for B in ti.grouped(m.blk_stamp):
        if m.blk_stamp[B] == stamp:
            wb = m.unwrap(B * LEAF, center)              # world voxel of the block's corner
            corner = wb.cast(ti.f32) * resolution
            reach = 0.0
            for q in range(LEAF * LEAF * LEAF):
                u = B * LEAF + ti.Vector([q // (LEAF * LEAF), (q // LEAF) % LEAF, q % LEAF])
                reach = ti.max(reach, m.ell[u])
            # the non-empty training blocks within reach of this block, looked up once
            lo = ti.floor((corner - reach) / blk_m, ti.i32)
            hi = ti.floor((corner + blk_m + reach) / blk_m, ti.i32)
            starts = ti.Vector([0] * MAX_LIST)
            counts = ti.Vector([0] * MAX_LIST)
            keys = ti.Vector([0] * MAX_LIST)
            n_list = 0
            span = hi - lo + 1
            for bx, by, bz in ti.ndrange((lo[0], hi[0] + 1), (lo[1], hi[1] + 1), (lo[2], hi[2] + 1)):
                sb = m.wrap_blk(ti.Vector([bx, by, bz]))
                n = m.s_bcount[sb]                      # 0, without activating, where empty
                if n > 0 and n_list < MAX_LIST:
                    starts[n_list] = m.s_bstart[sb]
                    counts[n_list] = n
                    keys[n_list] = ((bx - lo[0]) * span[1] + (by - lo[1])) * span[2] + (bz - lo[2])
                    n_list += 1
            for q in range(LEAF * LEAF * LEAF):
                u = B * LEAF + ti.Vector([q // (LEAF * LEAF), (q // LEAF) % LEAF, q % LEAF])
                ell = m.ell[u]
                if ell > 0:
                    centre = corner + (ti.Vector([q // (LEAF * LEAF), (q // LEAF) % LEAF, q % LEAF])
                                       .cast(ti.f32) + 0.5) * resolution
                    ell2 = ell * ell
                    acc = ti.Vector([0.0] * m.C)
                    for e in range(n_list):
                        k3 = keys[e]
                        b = lo + ti.Vector([k3 // (span[1] * span[2]), (k3 // span[2]) % span[1],
                                            k3 % span[2]])
                        b_lo = b.cast(ti.f32) * blk_m
                        if box_distance2(centre, b_lo, b_lo + blk_m) < ell2:
                            for p in range(starts[e], starts[e] + counts[e]):
                                d = ti.Vector([xyz[p, 0], xyz[p, 1], xyz[p, 2]]) - centre
                                d2 = d.dot(d)
                                if d2 < ell2:
                                    k = sigma0 * sparse_kernel(ti.sqrt(d2) / ell)
                                    mask = classes[p]
                                    for c in ti.static(range(1, m.C)):
                                        if mask & (1 << c):
                                            acc[c] += k * hist[p, c]
                    if acc.sum() > MIN_UPDATE:
                        fuse_voxel(m, u, acc, t, inv_tau)
