"""Step 9 and the map's host interface: query, count, export, import."""

import functools

import taichi as ti
from tisem.kernels.bki import sparse_kernel
from tisem.kernels.centroids import nearer_class


@ti.func
def inside_window(w, center, half):
    off = ti.abs(w - center)
    return off[0] <= half[0] and off[1] <= half[1] and off[2] <= half[2]


@ti.func
def blended_posterior(m: ti.template(), w, x, center, half, radius_m, inv_res):
    """Sum over the live voxels whose centres lie within radius_m of local point x (world
    voxel w) of g(d / radius) times the voxel's normalised counters: the continuous map's
    answer between its voxels (voxels the window does not hold are not read)."""
    reach = ti.cast(ti.ceil(radius_m * inv_res), ti.i32)
    res = 1.0 / inv_res
    acc = ti.Vector([0.0] * m.C)
    for dx in range(-reach, reach + 1):
        for dy in range(-reach, reach + 1):
            for dz in range(-reach, reach + 1):
                v = w + ti.Vector([dx, dy, dz])
                d = (x - (v.cast(ti.f32) + 0.5) * res).norm()
                if d < radius_m and inside_window(v, center, half):
                    u = m.wrap(v)
                    total = 0.0
                    for c in ti.static(range(m.C)):
                        total += m.counts[u, c]
                    if total > 0 and not m.is_empty(u):  # (space seen through says nothing)
                        k = sparse_kernel(d / radius_m) / total
                        for c in ti.static(range(m.C)):
                            acc[c] += k * m.counts[u, c]
    return acc


@ti.func
def answer(
    m: ti.template(), values, p, out_label: ti.template(), out_prob: ti.template(), with_prob
):
    """Point p's label (the argmax of values, 0 when all are 0) and, with_prob, the values
    normalised."""
    best = 0
    best_v = 0.0
    total = 0.0
    for c in ti.static(range(m.C)):
        v = values[c]
        total += v
        if v > best_v:
            best_v = v
            best = c
    if with_prob:
        for c in ti.static(range(m.C)):
            out_prob[p, c] = values[c] / total if total > 0 else 0.0
    out_label[p] = best


@ti.func
def lookup(
    m: ti.template(),
    w,
    x,
    center,
    half,
    p,
    out_label: ti.template(),
    out_inside: ti.template(),
    out_prob: ti.template(),
    with_prob,
    res,
    centroid_ratio,
):
    """Answer query point p (local coordinates x), whose world voxel is w: the argmax, or with
    class centroids the nearer of the two leading classes (kernels/centroids.py), and the
    normalised counters."""
    best = 0
    inside = 0
    if inside_window(w, center, half):
        inside = 1
        u = m.wrap(w)
        best_v = 0.0
        second = 0
        second_v = 0.0
        total = 0.0
        for c in ti.static(range(m.C)):
            v = m.counts[u, c]
            total += v
            if v > best_v:
                second = best
                second_v = best_v
                best_v = v
                best = c
            elif v > second_v:
                second = c
                second_v = v
        if ti.static(m.class_centroids):
            if second_v > 0 and second_v >= centroid_ratio * best_v:
                best = nearer_class(m, u, x - w.cast(ti.f32) * res, best, second, res)
        if m.is_empty(u):  # seen through (free space): it answers as no voxel does
            best = 0
            total = 0.0
        if with_prob:
            for c in ti.static(range(m.C)):
                out_prob[p, c] = m.counts[u, c] / total if total > 0 else 0.0
    out_label[p] = best
    out_inside[p] = inside


@functools.cache
def query_kernel(blend: bool):
    """The query kernel: voxel lookups only, or (`blend`) with the blended posterior for the
    points in the window whose voxel holds no evidence."""

    @ti.kernel
    def query(
        m: ti.template(),
        pts: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (N, 3) local coordinates, m
        center: ti.types.vector(3, ti.i32),
        half: ti.types.vector(3, ti.i32),
        inv_res: ti.f32,
        with_prob: ti.i32,  # 1: write out_prob
        radius_m: ti.f32,  # blend: the query radius
        res_m: ti.f32,  # the voxel size
        centroid_ratio: ti.f32,  # class centroids: the second class's share that splits a voxel
        out_label: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) train id, 0: no evidence
        out_inside: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) 1: the window covers it
        out_prob: ti.types.ndarray(dtype=ti.f32, ndim=2),
    ):  # (N, C), or (0, C): unused
        """Labels (and probabilities) of the points whose voxel the live window holds, the
        window being the box |w - center| <= half.

        `with_prob` is a runtime flag on purpose: as a compile-time choice, the compiler
        vectorises the 20-class total into a tree of additions in the kernel that writes
        probabilities, which rounds some of them differently in the last bit.
        """
        for p in range(out_label.shape[0]):
            x = ti.Vector([pts[p, 0], pts[p, 1], pts[p, 2]])
            w = ti.floor(x * inv_res, ti.i32)
            lookup(
                m,
                w,
                x,
                center,
                half,
                p,
                out_label,
                out_inside,
                out_prob,
                with_prob,
                res_m,
                centroid_ratio,
            )
            if ti.static(blend):
                # a point in the window whose voxel has no evidence (label 0: class 0 is never
                # evidence): the voxels around it; not in a voxel seen to be empty (free
                # space), whose answer is that nothing is there
                if out_inside[p] == 1 and out_label[p] == 0 and not m.is_empty(m.wrap(w)):
                    answer(
                        m,
                        blended_posterior(m, w, x, center, half, radius_m, inv_res),
                        p,
                        out_label,
                        out_prob,
                        with_prob,
                    )

    return query


@ti.kernel
def count_active(cells: ti.template()) -> ti.i32:
    """Active cells of a sparse field or SNode (m.t_last_rel: live voxels, m.blk: live blocks)."""
    n = 0
    for _ in ti.grouped(cells):
        n += 1
    return n


@ti.func
def copy_voxel_out(
    m: ti.template(),
    u,
    w,
    idx,
    keys: ti.template(),
    counts: ti.template(),
    t_last_rel: ti.template(),
    length_m: ti.template(),
):
    """Copy map voxel u (world index w) into row idx of the host arrays."""
    for a in ti.static(range(3)):
        keys[idx, a] = w[a]
    for c in ti.static(range(m.C)):
        counts[idx, c] = m.counts[u, c]
    t_last_rel[idx] = m.t_last_rel[u]
    length_m[idx] = m.length[u]


@ti.kernel
def export_voxels(
    m: ti.template(),
    center: ti.types.vector(3, ti.i32),
    keys: ti.types.ndarray(dtype=ti.i32, ndim=2),  # (M, 3) out: world voxel
    counts: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (M, C) out
    t_last_rel: ti.types.ndarray(dtype=ti.f32, ndim=1),  # (M,) out
    length_m: ti.types.ndarray(dtype=ti.f32, ndim=1),  # (M,) out
) -> ti.i32:
    """Every live voxel (world keys unwrapped at the window centre), in no particular order;
    returns how many there are (only the first M are written)."""
    m.counter[None] = 0
    for u in ti.grouped(m.t_last_rel):
        idx = ti.atomic_add(m.counter[None], 1)
        if idx < keys.shape[0]:
            copy_voxel_out(m, u, m.unwrap(u, center), idx, keys, counts, t_last_rel, length_m)
    return m.counter[None]


@ti.kernel
def import_voxels(
    m: ti.template(),
    keys: ti.types.ndarray(dtype=ti.i32, ndim=2),  # (M, 3) world voxel
    counts: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (M, C)
    t_last_rel: ti.types.ndarray(dtype=ti.f32, ndim=1),  # (M,)
    length_m: ti.types.ndarray(dtype=ti.f32, ndim=1),
):  # (M,)
    """Write voxels into the field (they become live), values as given."""
    for i in range(keys.shape[0]):
        u = m.wrap(ti.Vector([keys[i, 0], keys[i, 1], keys[i, 2]]))
        for c in ti.static(range(m.C)):
            m.counts[u, c] = counts[i, c]
        m.t_last_rel[u] = t_last_rel[i]
        m.length[u] = length_m[i]
