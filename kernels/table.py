"""The scan's table of leaf blocks (kernels/layout.py): handing out slices column by column,
and the reset after the scan.

Both of a scan's sorted orders, its points by block and its training rows by block, lay out
the blocks of each (x, y) column of the table one after another in z, so that any z-range of a
column is one contiguous slice. One kernel does that for both, given how to count a block.
"""

import taichi as ti
from tisem.kernels.layout import EMPTY_LO, LEAF, rows_to


@ti.func
def points_in(m: ti.template(), i):
    """The scan's points in table cell i."""
    return m.p_count[i]


@ti.func
def rows_in(m: ti.template(), i):
    """The scan's training rows in table cell i."""
    return rows_to(m.b_layers[i], LEAF - 1)


@ti.func
def column_count(m: ti.template(), count: ti.template(), cx, cy):
    """What column (cx, cy)'s z-range of cells holds (0 for an empty column: lo > hi)."""
    total = 0
    for cz in range(m.col_lo[cx, cy], m.col_hi[cx, cy] + 1):
        total += count(m, ti.Vector([cx, cy, cz]))
    return total


@ti.kernel
def column_slots(
    m: ti.template(), count: ti.template(), start: ti.template(), restart_count: ti.template()
) -> ti.i32:
    """Give every cell of every used column's z-range its first slot, empty cells too, the
    column's cells one after another in z and the columns in table order (x, then y); returns
    the total.

    `count(m, i)` counts cell i (points_in or rows_in), `start` is the field that gets the
    slots; with `restart_count` the counts (p_count) are zeroed to serve as fill cursors.

    The order is fixed, not first come first served: which training rows cast free-space
    rays (every stride-th row) follows it, so the same scans clear the same space whatever
    the threads do. A task per x row of the table counts it, one short serial pass turns the
    rows' counts into first slots, then a task per row again hands its slots out (a few
    hundred tasks: plenty for two CPU threads, few for a GPU, where this is not the costly
    step).
    """
    m.counter[None] = 0
    for cx in range(m.table_shape[0]):
        total = 0
        for cy in range(m.table_shape[1]):
            total += column_count(m, count, cx, cy)
        m.row_slots[cx] = total
    ti.loop_config(serialize=True)
    for cx in range(m.table_shape[0]):
        rows = m.row_slots[cx]
        m.row_slots[cx] = m.counter[None]
        m.counter[None] += rows
    for cx in range(m.table_shape[0]):
        slot = m.row_slots[cx]
        for cy in range(m.table_shape[1]):
            for cz in range(m.col_lo[cx, cy], m.col_hi[cx, cy] + 1):
                i = ti.Vector([cx, cy, cz])
                start[i] = slot
                slot += count(m, i)
                if ti.static(restart_count):
                    m.p_count[i] = 0
    return m.counter[None]


@ti.kernel
def clear_table(m: ti.template()):
    """Reset the scan's table: every cell of every used column's z-range."""
    for cx, cy in m.col_lo:
        lo, hi = m.col_lo[cx, cy], m.col_hi[cx, cy]
        if lo <= hi:
            for cz in range(lo, hi + 1):
                m.p_count[cx, cy, cz] = 0
                m.b_start[cx, cy, cz] = 0
                m.b_layers[cx, cy, cz] = 0
            m.col_lo[cx, cy] = EMPTY_LO
            m.col_hi[cx, cy] = -1
