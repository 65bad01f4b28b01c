"""The spatially sharded reduction of a fleet, and the scoring of its merged maps.

Each reducer owns a set of tiles (`assign_tiles`: by a hash of the tile, so every reducer
gets tiles from everywhere and the work evens out): for each of its tiles it reads that tile
from every task map that has it, merges them (`tisem.merge.merge_snapshots`) and writes the
merged tile. A reducer holds one tile at a time, never the map. `score_log` looks a log's
scans up in a merged tiled map (numpy only, no Taichi) for the final-map protocol.
Nothing here knows about Ray.
"""

from __future__ import annotations

import resource
import time
from pathlib import Path

import numpy as np

from tisem.evaluate import Confusion, network_labels, score_scan
from tisem.logs import LogSpec, open_log
from tisem.merge import merge_snapshots
from tisem.scan import Scan
from tisem.tiles import TiledMap, write_tile

__all__ = ["assign_tiles", "reduce_tiles", "score_log"]


def tile_owner(tile: tuple[int, int], reducers: int) -> int:
    x, y = (int(v) & 0xFFFFFFFF for v in tile)
    return ((x * 73856093) ^ (y * 19349663)) % max(int(reducers), 1)


def assign_tiles(tiles: list[tuple[int, int]], reducers: int) -> list[list[tuple[int, int]]]:
    """The tiles of each of `reducers` reducers (some may get none)."""
    owned: list[list[tuple[int, int]]] = [[] for _ in range(max(int(reducers), 1))]
    for tile in sorted(tiles):
        owned[tile_owner(tile, reducers)].append(tile)
    return owned


def reduce_tiles(
    out_dir: str, work: list[tuple[list[int], list[str]]], tau_s: float, mapper_config: dict
) -> dict:
    """Merge each (tile, task map folders that hold it) of `work` into `out_dir`'s tiles;
    returns the index entries, the bytes read and written, seconds and the peak memory."""
    started = time.perf_counter()
    entries, bytes_in, inputs = [], 0, 0
    maps: dict[str, TiledMap] = {}
    for tile, sources in work:
        tile = (int(tile[0]), int(tile[1]))
        parts = []
        for folder in sources:
            tiled = maps.setdefault(folder, TiledMap.open(folder, cache_tiles=1))
            entry = tiled.entry(tile)
            if entry is not None:
                bytes_in += int(entry["bytes"])
                parts.append(tiled.tile(tile))
        inputs += len(parts)
        if parts:
            entries.append(write_tile(out_dir, tile, merge_snapshots(parts, tau_s), mapper_config))
    return {
        "entries": entries,
        "tiles": len(entries),
        "tile_inputs": inputs,
        "bytes_read": bytes_in,
        "bytes_written": int(sum(e["bytes"] for e in entries)),
        "seconds": time.perf_counter() - started,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def score_log(
    map_dir: str, log: LogSpec, ranges: list[tuple[int, int]], input: str = "predictions"
) -> dict:
    """Confusions of the merged map (final-map protocol) and of the network's labels over the
    scans of `ranges` (positions, inclusive) of `log`, as C x C matrices."""
    tiled = TiledMap.open(map_dir, cache_tiles=64)
    final, network = Confusion(tiled.num_classes), Confusion(tiled.num_classes)
    scans = 0
    for first, last in ranges:
        for item in open_log(log, first, last, input=input, num_classes=tiled.num_classes):
            if not isinstance(item, Scan) or item.gt_labels is None:
                continue
            labels, _ = tiled.query(item.points_world(), with_probs=False)
            score_scan(final, item, labels)
            score_scan(network, item, network_labels(item))
            scans += 1
    return {
        "final": np.asarray(final.matrix).tolist(),
        "input": np.asarray(network.matrix).tolist(),
        "scans": scans,
        "tiles_loaded": tiled.tiles_loaded,
    }


def folder_bytes(folder: str | Path) -> int:
    return int(sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file()))
