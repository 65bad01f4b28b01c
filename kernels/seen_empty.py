"""The memory of space seen empty where the map holds no voxel (free space, seen_empty_s > 0).

A ray that crosses a voxel the map does not hold writes there the map time until which
whatever lands in it is dynamic (kernels/raycast.py: DUFOMap's rule, that space seen empty at
one time makes what is in it at another time dynamic, held for seen_empty_s). This module
forgets: every leaf block whose voxels have all expired goes, then every top cell left without
blocks (a pointer cell is freed only after its children: taichi 1.7.4 leaks the children of a
freed one), so the memory holds the space the rays of the last seen_empty_s seconds crossed.
"""

import taichi as ti
from tisem.kernels.layout import LEAF, MID, deactivate, local_of_index


@ti.kernel
def forget_expired_blocks(m: ti.template(), now: ti.f32) -> ti.i32:
    """Free the blocks of the memory whose every voxel expired by `now`; returns how many
    blocks stay."""
    kept = 0
    for b in ti.grouped(m.seen_blk):
        latest = 0.0
        for q in range(LEAF * LEAF * LEAF):
            latest = ti.max(latest, m.empty_until[b * LEAF + local_of_index(q)])
        if latest <= now:
            deactivate(m.seen_blk, b)
        else:
            kept += 1
    return kept


@ti.kernel
def forget_empty_tops(m: ti.template()):
    """Free the top cells of the memory that hold no block."""
    for t in ti.grouped(m.seen_top):
        used = 0
        for q in range(MID * MID * MID):
            o = ti.Vector([q % MID, (q // MID) % MID, q // (MID * MID)])
            if ti.is_active(m.seen_blk, t * MID + o):
                used = 1
        if not used:
            deactivate(m.seen_top, t)
