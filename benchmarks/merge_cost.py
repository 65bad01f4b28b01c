"""What merging costs per voxel: the per-voxel merge, writing tiles, reading them back.

    python benchmarks/merge_cost.py                  # two maps of 10^6 voxels
    python benchmarks/merge_cost.py --voxels 200000 --json merge.json

Two maps of random voxels (three non-zero classes of 20 each, random update times), half of
their area shared, are merged with `tisem.merge.merge_snapshots` (tau 5 s), the result is
split into tiles and written (`tisem.tiles.write_tile`, compressed map files) and read back
tile by tile (`TiledMap.tile`). numpy only: no Taichi, no Ray. These are the per-voxel costs
docs/scale.md projects a reduction from.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import benchmark_main


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--voxels", type=int, default=1_000_000, help="voxels per map")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json")
    return p.parse_args(argv)


def random_map(rng, n: int, shift_x: int):
    from tisem.snapshot import MapSnapshot

    span_x = max(int(np.sqrt(n)) * 2, 8)
    keys = np.c_[
        rng.integers(0, span_x, n) + shift_x,
        rng.integers(0, span_x // 3, n),
        rng.integers(0, 30, n),
    ]
    keys = np.unique(keys, axis=0)
    keys = keys[MapSnapshot.sort_order(keys)]
    counts = np.zeros((len(keys), 20), np.float32)
    classes = rng.integers(0, 20, (len(keys), 3))
    np.put_along_axis(counts, classes, rng.uniform(0, 5, classes.shape).astype(np.float32), 1)
    return MapSnapshot(
        keys, counts, rng.uniform(0, 100, len(keys)), np.full(len(keys), 0.8, np.float32), 0.2
    ), span_x


def run(args) -> dict:
    from tisem.merge import merge_snapshots
    from tisem.tiles import TiledMap, TileIndex, split_by_tile, write_index, write_tile

    rng = np.random.default_rng(args.seed)
    a, span_x = random_map(rng, args.voxels, 0)
    b, _ = random_map(rng, args.voxels, span_x // 2)
    start = time.perf_counter()
    merged = merge_snapshots([a, b], 5.0)
    merge_s = time.perf_counter() - start
    config = {"mode": "st", "resolution_m": 0.2, "num_classes": 20}
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        entries = [write_tile(folder, t, part, config) for t, part in split_by_tile(merged)]
        write_s = time.perf_counter() - start
        write_index(folder, TileIndex(0.2, 20, 256, "bench", config, entries, {}))
        tiled = TiledMap.open(folder, cache_tiles=1)
        start = time.perf_counter()
        read = sum(len(tiled.tile(t)) for t in tiled.tile_keys)
        read_s = time.perf_counter() - start
    n = len(merged)
    assert read == n
    return {
        "rows": len(a) + len(b),
        "voxels": n,
        "tiles": len(entries),
        "merge_us_per_voxel": 1e6 * merge_s / n,
        "write_us_per_voxel": 1e6 * write_s / n,
        "read_us_per_voxel": 1e6 * read_s / n,
        "bytes_per_voxel": sum(e["bytes"] for e in entries) / n,
    }


def format_result(r: dict) -> str:
    return (
        f"{r['rows']:,} rows -> {r['voxels']:,} voxels in {r['tiles']} tiles: merge "
        f"{r['merge_us_per_voxel']:.2f} us, write {r['write_us_per_voxel']:.2f} us, read "
        f"{r['read_us_per_voxel']:.2f} us per voxel; {r['bytes_per_voxel']:.1f} B per "
        f"voxel on disk"
    )


def main(argv=None) -> int:
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
