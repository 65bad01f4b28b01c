"""The block cap within one scan: how many leaf blocks a scan may make live, and which of its
points it keeps when it would make more.

taichi 1.7.4's CPU allocator corrupts memory once the sparse pools need a second 1 GiB chunk
(from ~147,000 live leaf blocks on), so the live blocks never exceed `max_live_blocks`, scan
by scan: the scan's points are sorted into the dense table of leaf blocks before any kernel
activates a block, so the blocks it would add are known first. A scan that would take more
than the room left under the cap takes at most half of that room (the scans that follow at the
same place still find room), keeping every point in a block already live and in the new blocks
nearest the sensor; the rest is dropped, with the numbers in one line. A scan left with no
point at all is refused.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from taichi.lang.argpack import ArgPack

from tisem.kernels.layout import LEAF, MapFields
from tisem.kernels.rasterize import DROPPED
from tisem.kernels.window import flag_new_blocks


@dataclass
class Cut:
    """Which points a too-dense scan keeps, and the numbers its message gives."""

    keep: np.ndarray  # (N,) bool over the scan's points
    new_blocks: int  # new leaf blocks the whole scan would have made live
    kept_blocks: int  # of them, the ones kept (the nearest)
    free_blocks: int  # room under the cap before the scan
    reach_m: float  # how far from the sensor's block the farthest kept new block lies

    def describe(self, where: str, cap: int, used: int) -> str:
        kept = int(np.count_nonzero(self.keep))
        return (
            f"{where}: too dense for the block cap: its {used:,} points need "
            f"{self.new_blocks:,} new leaf blocks, {self.free_blocks:,} of "
            f"max_live_blocks={cap:,} are free; kept the points in live blocks and in the "
            f"{self.kept_blocks:,} nearest new blocks (within {self.reach_m:.1f} m): "
            f"{kept:,} points mapped, {used - kept:,} dropped"
        )

    def refusal(self, where: str, cap: int, used: int) -> str:
        return (
            f"{where}: too dense for the block cap: its {used:,} points need "
            f"{self.new_blocks:,} new leaf blocks and only {self.free_blocks:,} of "
            f"max_live_blocks={cap:,} are free, none of them in a live block; skipped"
        )


def new_blocks_beyond(
    fields: MapFields, params: ArgPack, cells: np.ndarray, free_blocks: int
) -> np.ndarray | None:
    """None when the scan's occupied table cells (`cells`) cannot make more than `free_blocks`
    leaf blocks live; else per cell 1 where it would add a new block (kernels/window.py).
    Only a scan with more occupied cells than room pays for the test."""
    if len(cells) <= free_blocks:
        return None
    new = np.zeros(len(cells), np.int32)
    if flag_new_blocks(fields, params, cells, new) <= free_blocks:
        return None
    return new


def blocks_allowed(free_blocks: int) -> int:
    """New blocks a scan that does not fit may still make live: half the room left."""
    return max(int(free_blocks), 0) // 2


def cut_to_nearest(
    point_cell: np.ndarray,
    cells: np.ndarray,
    new: np.ndarray,
    table_shape: tuple,
    table_half: tuple,
    free_blocks: int,
    resolution_m: float,
) -> Cut:
    """The points to keep: those in occupied table cells (`cells`, sorted ids) that are not
    new (`new` 0) and those in the `blocks_allowed(free_blocks)` new cells nearest the sensor's
    block (ties by cell id: deterministic). `point_cell` is each point's cell id (DROPPED: not
    located)."""
    allowed = blocks_allowed(free_blocks)
    idx = np.stack(np.unravel_index(cells, table_shape), axis=1) - np.asarray(table_half)
    d2 = np.einsum("ij,ij->i", idx, idx)
    new_at = np.flatnonzero(new)
    nearest = new_at[np.lexsort((cells[new_at], d2[new_at]))[:allowed]]
    keep_cell = new == 0
    keep_cell[nearest] = True
    located = point_cell != DROPPED
    slot = np.searchsorted(cells, point_cell[located])
    keep = np.zeros(len(point_cell), bool)
    keep[np.flatnonzero(located)[keep_cell[slot]]] = True
    reach = float(np.sqrt(d2[nearest].max())) * LEAF * resolution_m if len(nearest) else 0.0
    return Cut(keep, len(new_at), len(nearest), int(free_blocks), reach)
