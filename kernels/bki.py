"""Steps 6-7: the compact-support sparse kernel and the Bayesian kernel update.

Every training point adds k(v, p) * h(p) to each live map voxel v whose centre lies within
that voxel's own kernel length L(v); contributions are summed with atomic adds into the scan
layer's delta, which fusion then folds into the map.
"""
import math

import taichi as ti


@ti.func
def sparse_kernel(r):
    """Melkumyan-Ramos g(r) for r = d / L in [0, 1): 1 at r = 0, 0 with zero slope at r = 1."""
    two_pi_r = 2.0 * math.pi * r
    return (2.0 + ti.cos(two_pi_r)) / 3.0 * (1.0 - r) + ti.sin(two_pi_r) / (2.0 * math.pi)


@ti.kernel
def scatter(m: ti.template(),
            xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),     # (K, 3) training points, local m
            hist: ti.types.ndarray(dtype=ti.f32, ndim=2),    # (K, C) their class evidence
            n: ti.i32, resolution: ti.f32, reach: ti.f32, sigma0: ti.f32, radius_vox: ti.i32):
    inv_res = 1.0 / resolution
    reach2 = reach * reach
    for p in range(n):
        pos = ti.Vector([xyz[p, 0], xyz[p, 1], xyz[p, 2]])
        h = ti.Vector([0.0] * m.C)
        for c in ti.static(range(m.C)):
            h[c] = hist[p, c]
        base = ti.floor(pos * inv_res, ti.i32)
        for dx, dy, dz in ti.ndrange((-radius_vox, radius_vox + 1), (-radius_vox, radius_vox + 1),
                                     (-radius_vox, radius_vox + 1)):
            w = base + ti.Vector([dx, dy, dz])
            d = (w.cast(ti.f32) + 0.5) * resolution - pos
            d2 = d.dot(d)
            if d2 < reach2:
                u = m.wrap(w)
                ell = m.ell[u]               # 0 where no map voxel lives
                if ell > 0 and d2 < ell * ell:
                    k = sigma0 * sparse_kernel(ti.sqrt(d2) / ell)
                    for c in ti.static(range(1, m.C)):
                        if h[c] > 0:
                            m.s_delta[u, c] += k * h[c]
