"""Free space: rays from the sensor to a scan's hits, and the occupancy evidence they leave.

A ray runs from the sensor's position to a training point (the centroid of a hit voxel; one
ray per `free_ray_stride` of them) and stops a margin before it,
`max(margin_m, margin_fraction * range)`: the last stretch of a ray grazing the ground runs
within a voxel of the surface it hits, and counting it as free would erase the road. One
thread per ray walks the voxels the ray crosses
(a 3-D DDA, Amanatides & Woo 1987): from the sensor's voxel, step along the axis whose next
voxel face the ray reaches first; axes that reach a face at the same parameter (a ray through
an edge or a corner) step together, so no voxel the ray only touches is visited.

Crossed voxels that exist lose occupancy evidence; a voxel the scan hits gains it. Both decay
with the voxel's counters (kernels/fusion.py) and are clamped to +-cap, so a long-parked car
clears after a bounded number of scans once it is gone. Free space never makes a map voxel
live: a ray through space the map holds no voxel in only writes the memory of space seen empty
(kernels/seen_empty.py, when seen_empty_s > 0), a tree of its own. Each voxel changes at most
once per scan (`free_stamp`), whatever the number of rays through it, and neither a voxel hit
by the scan nor one next to it is made free by it (a ray grazing a surface it also hits).
"""

import functools

import taichi as ti
from tisem.kernels.fusion import decay_voxel_to
from tisem.kernels.params import ScanParams
from tisem.kernels.rasterize import to_local

# parameters of one ray's faces closer than this (fractions of the ray) count as one: a ray
# through a voxel edge or corner steps every axis at once
TIE_T = 1.0e-6
NEVER = 1.0e30  # the parameter at which a ray parallel to an axis reaches its next face


@ti.func
def free_fraction(length_m, margin_m, margin_fraction):
    """The part of a ray of length_m, from the sensor, that is free: all but the margin."""
    free = 0.0
    if length_m > 0:
        free = (length_m - ti.max(margin_m, margin_fraction * length_m)) / length_m
    return free


@ti.func
def traverse(o, e, t_stop, visit: ti.template(), a0: ti.template(), a1: ti.template(), r):
    """Call visit(a0, a1, r, v) for every voxel v the segment o + t (e - o), 0 <= t < t_stop
    crosses, in order (o, e in voxel units: metres * 1/resolution). Nothing when t_stop <= 0."""
    d = e - o
    v = ti.floor(o, ti.i32)
    step = ti.Vector([0, 0, 0])
    ahead = ti.Vector([0, 0, 0])  # 1: the next face along the axis is the voxel's upper one
    t_max = ti.Vector([NEVER, NEVER, NEVER])
    for a in ti.static(range(3)):
        if d[a] > 0:
            step[a] = 1
            ahead[a] = 1
        elif d[a] < 0:
            step[a] = -1
            if v[a] == o[a]:  # (starting on a face, going down: the voxel below it)
                v[a] -= 1
        if d[a] != 0:
            t_max[a] = (v[a] + ahead[a] - o[a]) / d[a]
    if t_stop > 0:
        visit(a0, a1, r, v)
        # a bound on the steps, should rounding ever keep t_max below t_stop
        last = ti.floor(e, ti.i32)
        steps = ti.abs(last[0] - v[0]) + ti.abs(last[1] - v[1]) + ti.abs(last[2] - v[2]) + 3
        k = 0
        while k < steps:
            t_next = ti.min(t_max[0], t_max[1], t_max[2])
            if t_next >= t_stop:
                break
            for a in ti.static(range(3)):
                if t_max[a] <= t_next + TIE_T:
                    v[a] += step[a]
                    # the face's parameter anew, not by adding 1/d per step: a sum of hundreds
                    # of float32 steps drifts past the tie tolerance
                    t_max[a] = (v[a] + ahead[a] - o[a]) / d[a]
            visit(a0, a1, r, v)
            k += 1


@ti.func
def _record(out_voxels: ti.template(), out_count: ti.template(), r, v):
    n = out_count[r]
    if n < out_voxels.shape[1]:
        for a in ti.static(range(3)):
            out_voxels[r, n, a] = v[a]
    out_count[r] = n + 1


@ti.kernel
def trace_rays(
    origins: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (R, 3) metres
    ends: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (R, 3) metres
    inv_res: ti.f32,
    margin_m: ti.f32,
    margin_fraction: ti.f32,
    out_voxels: ti.types.ndarray(dtype=ti.i32, ndim=3),  # (R, K, 3) out: in order
    out_count: ti.types.ndarray(dtype=ti.i32, ndim=1),
):  # (R,) out: voxels crossed
    """The voxels each ray crosses (the first K of them), as the map's free-space pass walks
    them: what tests compare with an exact reference."""
    for r in range(origins.shape[0]):
        o = ti.Vector([origins[r, 0], origins[r, 1], origins[r, 2]])
        e = ti.Vector([ends[r, 0], ends[r, 1], ends[r, 2]])
        out_count[r] = 0
        t_stop = free_fraction((e - o).norm(), margin_m, margin_fraction)
        traverse(o * inv_res, e * inv_res, t_stop, _record, out_voxels, out_count, r)


# A live voxel's free_stamp: 2 * scan + 1 when the scan hit it, 2 * scan when its rays crossed
# it (a hit outranks a crossing under atomic_max)
@ti.func
def hit_stamp(stamp):
    return 2 * stamp + 1


@ti.func
def crossed_stamp(stamp):
    return 2 * stamp


@ti.func
def beside_hit(m: ti.template(), w, hit):
    """Whether a voxel next to world voxel w (of the 26) was hit by the scan (free_stamp ==
    hit). A ray that passes a surface the scan hits crosses the voxels it is partly in (a
    voxel is more than the surface in it: a pole, a trunk, an edge): those keep their
    evidence, as DUFOMap keeps the voxels next to a hit out of its free space."""
    near = False
    for o in ti.grouped(ti.ndrange((-1, 2), (-1, 2), (-1, 2))):
        if m.free_stamp[m.wrap(w + o)] == hit:  # (0 in a voxel that is not live)
            near = True
    return near


@functools.cache
def free_space_kernels(decay: str):
    """The map's free-space kernels for one decay rule (kernels/params.py)."""

    @ti.func
    def lose_evidence(m: ti.template(), s: ti.template(), u):
        """Live voxel u was seen through by the scan: one less occupancy evidence."""
        decay_voxel_to(m, u, s.time_rel_s, s.inv_tau, decay)
        m.occupancy[u] = ti.max(m.occupancy[u] - 1.0, -m.occupancy_cap)
        ti.atomic_add(m.counter[None], 1)

    @ti.func
    def make_free(m: ti.template(), s: ti.template(), r, v):
        u = m.wrap(v)
        if ti.is_active(m.vox, u):
            # the first ray of the scan through u decides, the others find its stamp (a voxel
            # the scan hit holds the higher one)
            crossed = crossed_stamp(s.stamp)
            if m.free_stamp[u] < crossed:
                if ti.atomic_max(m.free_stamp[u], crossed) < crossed:
                    # (nested: Taichi evaluates both sides of an `and`, and the spare's count
                    # of crossings must not grow in a scan that hit the voxel's neighbours)
                    if not beside_hit(m, v, hit_stamp(s.stamp)):
                        if not thin_static_led(m, s, u):
                            if ti.static(m.spare_beside_unseen):
                                # decided by clear_crossed, once every ray has written the memory
                                i = ti.atomic_add(m.n_crossed[None], 1)
                                if i < m.crossed.shape[0]:
                                    m.crossed[i] = v
                                else:  # (more than the list holds: these go without the check)
                                    lose_evidence(m, s, u)
                            else:
                                lose_evidence(m, s, u)
        elif ti.static(m.seen_empty_s > 0):
            # space the map holds nothing in: remembered as seen empty. Written without reading
            # first: every ray writes the same value, the first one through a voxel allocates
            # its block either way, and a write alone costs less than a read and an
            # unpredictable branch (the cast ~20 % faster on real scans)
            m.empty_until[u] = s.time_rel_s + m.seen_empty_s

    @ti.kernel
    def mark_hits(
        m: ti.template(),
        s: ScanParams,
        xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (K, 3) training points, local
        n_rows: ti.i32,
    ):
        """Every voxel holding a training point of the scan gains a hit (and is not made free
        by the scan's rays)."""
        for r in range(n_rows):
            u = m.wrap(
                ti.floor(ti.Vector([xyz[r, 0], xyz[r, 1], xyz[r, 2]]) * s.inv_resolution, ti.i32)
            )
            if ti.is_active(m.vox, u):
                decay_voxel_to(m, u, s.time_rel_s, s.inv_tau, decay)
                m.occupancy[u] = ti.min(m.occupancy[u] + 1.0, m.occupancy_cap)
                m.free_stamp[u] = hit_stamp(s.stamp)
                if ti.static(m.thin_static_hold):
                    m.hit_time[u] = s.time_rel_s
                    if m.first_hit[u] == 0.0:
                        m.first_hit[u] = 1.0 + s.time_rel_s
                if ti.static(m.thin_static_crossings):
                    m.crossings_since_hit[u] = 0

    @ti.kernel
    def cast_free(
        m: ti.template(),
        s: ScanParams,
        xyz: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (K, 3) ray ends, local
        n_rows: ti.i32,
        stride: ti.i32,
        margin_m: ti.f32,
        margin_fraction: ti.f32,
    ) -> ti.i32:
        """One ray per `stride` training points (their rows are sorted by leaf block, so every
        stride-th is spread over the scan); returns how many voxels lost occupancy evidence."""
        m.counter[None] = 0
        o = s.translation_m
        for q in range((n_rows + stride - 1) // stride):
            r = q * stride
            e = ti.Vector([xyz[r, 0], xyz[r, 1], xyz[r, 2]])
            t_stop = free_fraction((e - o).norm(), margin_m, margin_fraction)
            traverse(o * s.inv_resolution, e * s.inv_resolution, t_stop, make_free, m, s, r)
        return m.counter[None]

    @ti.kernel
    def clear_crossed(m: ti.template(), s: ScanParams) -> ti.i32:
        """After the scan's rays (spare_beside_unseen): the live voxels they crossed lose
        evidence, except those next to space no ray has seen; returns how many lost it."""
        m.counter[None] = 0
        for i in range(ti.min(m.n_crossed[None], m.crossed.shape[0])):
            v = m.crossed[i]
            if not beside_unseen(m, s, v):
                lose_evidence(m, s, m.wrap(v))
        m.n_crossed[None] = 0
        return m.counter[None]

    return mark_hits, cast_free, clear_crossed


@ti.func
def beside_unseen(m: ti.template(), s: ti.template(), w):
    """1 when a voxel next to world voxel w (of the 26) is neither in the map nor remembered
    as seen empty. A surface is seen from one side: the space behind it is never crossed, so a
    voxel a ray crossed in front of a surface (a voxel is more than the surface in it) borders
    unseen space, while an object that moves into space seen empty is surrounded by it."""
    near = 0
    for o in ti.grouped(ti.ndrange((-1, 2), (-1, 2), (-1, 2))):
        u = m.wrap(w + o)
        if not ti.is_active(m.vox, u):
            if m.empty_until[u] <= s.time_rel_s:
                near = 1
    return near


@ti.func
def leading_class(m: ti.template(), u):
    """The class with the most evidence in live voxel u (0 when it holds none)."""
    best = 0
    top = 0.0
    for c in ti.static(range(1, m.C)):
        if m.counts[u, c] > top:
            top = m.counts[u, c]
            best = c
    return best


@ti.func
def thin_static_led(m: ti.template(), s: ti.template(), u):
    """1 when live voxel u is led by a thin class that cannot move and rays are to leave it
    (spare_thin_static): rays graze thin structure sampled sparsely. 0 with the rule off, and
    (thin_static_hold_s) when the scans' hits of u came and went within the hold and none has
    hit it for longer than that: a pole or a trunk is hit now and then for as long as it is
    in view, while a voxel a walker made with the network's trunk or pole labels is hit only
    in the few scans the walker is in it. (A voxel no scan hit keeps that spare.) Also 0
    (thin_static_crossings) once the spare has kept u through more scans of crossings than
    the limit since its last hit (each call is such a scan; counted only while the spare
    holds, so that no other voxel pays a write): a pole in view is hit again before many
    scans see through its voxel, while the place a group of walkers left, hit over more than
    the hold, is seen through scan after scan."""
    led = 0
    if ti.static(m.spare_thin_static):
        lapsed = False  # checked first: it skips the loop over the classes
        if ti.static(m.thin_static_hold):
            hold = m.thin_static_hold_s
            if m.first_hit[u] > 0.0 and s.time_rel_s - m.hit_time[u] > hold:
                lapsed = m.hit_time[u] - (m.first_hit[u] - 1.0) < hold
        if not lapsed:
            led = m.thin_static_class[leading_class(m, u)]
            if ti.static(m.thin_static_crossings):
                if led == 1:
                    n = m.crossings_since_hit[u] + 1
                    m.crossings_since_hit[u] = n
                    if n > m.thin_static_crossings_n:
                        led = 0
    return led


@ti.func
def beside_own_class(m: ti.template(), w, c):
    """Whether a live voxel next to world voxel w (of the 26) is led by class c (a static
    structure goes on there: what moves into space seen empty is surrounded by it, or by
    voxels of other classes, like a car by the road under it)."""
    near = False
    for o in ti.grouped(ti.ndrange((-1, 2), (-1, 2), (-1, 2))):
        u = m.wrap(w + o)
        if ti.is_active(m.vox, u):
            if leading_class(m, u) == c:
                near = True
    return near


@ti.kernel
def flag_dynamic(
    m: ti.template(),
    s: ScanParams,
    pts: ti.types.ndarray(dtype=ti.f32, ndim=2),  # (N, k >= 3) sensor frame: x y z first
    labels: ti.types.ndarray(dtype=ti.i32, ndim=1),  # (N,) the points' classes
    half: ti.types.vector(3, ti.i32),  # the live window's half-size
    out: ti.types.ndarray(dtype=ti.i8, ndim=1),
) -> ti.i32:  # (N,) out: 1 dynamic
    """Flag the points that land in a live voxel observed empty, or where the map holds no
    voxel in space a ray saw empty less than seen_empty_s ago (before this scan's rays), except
    next to space no ray has seen, and (spare_static_beside_own) a point of a class that
    cannot move next to a live voxel its class leads; returns how many."""
    n = 0
    R = s.rotation
    for p in range(pts.shape[0]):
        x = to_local(R, ti.Vector([pts[p, 0], pts[p, 1], pts[p, 2]]), s.translation_m)
        rel = x * s.inv_resolution - s.center_vox
        flag = 0
        # (compared as floats first: a far point's voxel index would not fit an int32)
        if ti.abs(rel[0]) <= half[0] and ti.abs(rel[1]) <= half[1] and ti.abs(rel[2]) <= half[2]:
            w = ti.floor(x * s.inv_resolution, ti.i32)
            u = m.wrap(w)
            if ti.is_active(m.vox, u):
                if m.is_empty(u):
                    flag = 1
            elif ti.static(m.seen_empty_s > 0):
                if m.empty_until[u] > s.time_rel_s:  # (0 where no ray has been)
                    flag = 1 - beside_unseen(m, s, w)
                    if ti.static(m.spare_static_beside_own):
                        # a pole or a trunk sampled sparsely: rays passed beside it through
                        # voxels it is partly in, before a scan hit it there
                        if flag == 1 and m.static_class[labels[p]] == 1:
                            if beside_own_class(m, w, labels[p]):
                                flag = 0
        out[p] = ti.cast(flag, ti.i8)
        n += flag
    return n


@ti.kernel
def gather_occupancy(
    m: ti.template(),
    keys: ti.types.ndarray(dtype=ti.i32, ndim=2),  # (M, 3) live voxels
    out: ti.types.ndarray(dtype=ti.f32, ndim=1),
):  # (M,) out
    """The occupancy evidence of the given live voxels."""
    for i in range(keys.shape[0]):
        out[i] = m.occupancy[m.wrap(ti.Vector([keys[i, 0], keys[i, 1], keys[i, 2]]))]


@ti.kernel
def scatter_occupancy(
    m: ti.template(),
    keys: ti.types.ndarray(dtype=ti.i32, ndim=2),  # (M, 3) live voxels
    occupancy: ti.types.ndarray(dtype=ti.f32, ndim=1),
    t_last_rel: ti.types.ndarray(dtype=ti.f32, ndim=1),  # (M,) their last update
):
    """Write the occupancy evidence of voxels just imported into the window. With a
    thin_static_hold_s, a voxel back from the store counts as hit from the map's first scan
    to its last update (the store keeps no hit times): structure that has stood, whose spare
    holds. (Its count of crossings since a hit is 0, as export_leaving left it.)"""
    for i in range(keys.shape[0]):
        u = m.wrap(ti.Vector([keys[i, 0], keys[i, 1], keys[i, 2]]))
        m.occupancy[u] = occupancy[i]
        if ti.static(m.thin_static_hold):
            m.hit_time[u] = t_last_rel[i]
            m.first_hit[u] = 1.0
