"""Step 9 and the map's host interface: query, count, export, import."""
import taichi as ti


@ti.func
def lookup(m: ti.template(), w, center, half, p, out_label: ti.template(),
           out_inside: ti.template(), out_prob: ti.template(), with_prob):
    """Answer query point p, whose world voxel is w: argmax and normalised counters."""
    off = ti.abs(w - center)
    best = 0
    inside = 0
    if off[0] <= half[0] and off[1] <= half[1] and off[2] <= half[2]:
        inside = 1
        u = m.wrap(w)
        best_v = 0.0
        total = 0.0
        for c in ti.static(range(m.C)):
            v = m.counts[u, c]
            total += v
            if v > best_v:
                best_v = v
                best = c
        if m.is_empty(u):   # seen through (free space): it answers as no voxel does
            best = 0
            total = 0.0
        if with_prob:
            for c in ti.static(range(m.C)):
                out_prob[p, c] = m.counts[u, c] / total if total > 0 else 0.0
    out_label[p] = best
    out_inside[p] = inside


@ti.kernel
def query(m: ti.template(),
          pts: ti.types.ndarray(dtype=ti.f32, ndim=2),        # (N, 3) local coordinates, m
          center: ti.types.vector(3, ti.i32), half: ti.types.vector(3, ti.i32), inv_res: ti.f32,
          with_prob: ti.i32,                                  # 1: write out_prob
          out_label: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) train id, 0: no evidence
          out_inside: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) 1: the window covers it
          out_prob: ti.types.ndarray(dtype=ti.f32, ndim=2)):  # (N, C), or (0, C): unused
    """Labels (and probabilities) of the points whose voxel the live window holds, the window
    being the box |w - center| <= half.

    `with_prob` is a runtime flag on purpose: as a compile-time choice, the compiler vectorises
    the 20-class total into a tree of additions in the kernel that writes probabilities, which
    rounds some of them differently in the last bit.
    """
    for p in range(out_label.shape[0]):
        w = ti.floor(ti.Vector([pts[p, 0], pts[p, 1], pts[p, 2]]) * inv_res, ti.i32)
        lookup(m, w, center, half, p, out_label, out_inside, out_prob, with_prob)


@ti.kernel
def count_active(cells: ti.template()) -> ti.i32:
    """Active cells of a sparse field or SNode (m.t_last_rel: live voxels, m.blk: live blocks)."""
    n = 0
    for _ in ti.grouped(cells):
        n += 1
    return n


@ti.func
def copy_voxel_out(m: ti.template(), u, w, idx, keys: ti.template(), counts: ti.template(),
                   t_last_rel: ti.template(), length_m: ti.template()):
    """Copy map voxel u (world index w) into row idx of the host arrays."""
    for a in ti.static(range(3)):
        keys[idx, a] = w[a]
    for c in ti.static(range(m.C)):
        counts[idx, c] = m.counts[u, c]
    t_last_rel[idx] = m.t_last_rel[u]
    length_m[idx] = m.length[u]


@ti.kernel
def export_voxels(m: ti.template(), center: ti.types.vector(3, ti.i32),
                  keys: ti.types.ndarray(dtype=ti.i32, ndim=2),        # (M, 3) out: world voxel
                  counts: ti.types.ndarray(dtype=ti.f32, ndim=2),      # (M, C) out
                  t_last_rel: ti.types.ndarray(dtype=ti.f32, ndim=1),  # (M,) out
                  length_m: ti.types.ndarray(dtype=ti.f32, ndim=1)     # (M,) out
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
def import_voxels(m: ti.template(),
                  keys: ti.types.ndarray(dtype=ti.i32, ndim=2),        # (M, 3) world voxel
                  counts: ti.types.ndarray(dtype=ti.f32, ndim=2),      # (M, C)
                  t_last_rel: ti.types.ndarray(dtype=ti.f32, ndim=1),  # (M,)
                  length_m: ti.types.ndarray(dtype=ti.f32, ndim=1)):   # (M,)
    """Write voxels into the field (they become live), values as given."""
    for i in range(keys.shape[0]):
        u = m.wrap(ti.Vector([keys[i, 0], keys[i, 1], keys[i, 2]]))
        for c in ti.static(range(m.C)):
            m.counts[u, c] = counts[i, c]
        m.t_last_rel[u] = t_last_rel[i]
        m.length[u] = length_m[i]
