"""Step 2 of the method: rasterise a scan into the scan layer (histogram, count, coordinate sum)."""
import taichi as ti


@ti.kernel
def rasterize_labels(m: ti.template(),
                     vox: ti.types.ndarray(dtype=ti.i32, ndim=2),      # (N, 3) world voxel index
                     xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),      # (N, 3) local coordinates, m
                     label: ti.types.ndarray(dtype=ti.i32, ndim=1)):   # (N,) train id in [0, C)
    for p in range(label.shape[0]):
        u = m.wrap(ti.Vector([vox[p, 0], vox[p, 1], vox[p, 2]]))
        m.s_npts[u] += 1
        for a in ti.static(range(3)):
            m.s_sum[u, a] += xyz[p, a]
        if label[p] > 0:  # train id 0 (unlabeled) counts as a point but adds no class evidence
            m.s_hist[u, label[p]] += 1.0


@ti.kernel
def rasterize_probs(m: ti.template(),
                    vox: ti.types.ndarray(dtype=ti.i32, ndim=2),       # (N, 3)
                    xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),       # (N, 3)
                    prob: ti.types.ndarray(dtype=ti.f32, ndim=2)):     # (N, C), class 0 ignored
    for p in range(prob.shape[0]):
        u = m.wrap(ti.Vector([vox[p, 0], vox[p, 1], vox[p, 2]]))
        m.s_npts[u] += 1
        for a in ti.static(range(3)):
            m.s_sum[u, a] += xyz[p, a]
        for c in ti.static(range(1, m.C)):
            if prob[p, c] > 0:
                m.s_hist[u, c] += prob[p, c]


@ti.kernel
def clear_scan_layer(m: ti.template()):
    """Free every scan-layer leaf block (its memory is recycled zero-filled), then the top cells."""
    for I in ti.grouped(m.s_blk):
        ti.deactivate(m.s_blk, I)


@ti.kernel
def clear_scan_top(m: ti.template()):
    for I in ti.grouped(m.s_top):
        ti.deactivate(m.s_top, I)
