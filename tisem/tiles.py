"""Tiled maps: a map too big for one process, as a folder of tiles plus an index.

    tiled = TiledMap.open("results/fleet/maps/robots")    # reads only tiles.json
    labels, probs = tiled.query(points_world)             # loads the tiles the points fall in
    snap = tiled.snapshot(max_voxels=20_000_000)          # the whole map, when it fits

A tile is a column of TILE_VOX x TILE_VOX voxels in x and y (every height), a multiple of the
SNode tree's top cell so tiles line up with the engine's blocks. Each tile is an ordinary map
file (`tisem.io.mapfile`, atomic, pickle-free) under `tiles/`; `tiles.json` lists every tile
with its voxel count and time range, the map's resolution, class count, mapper config and world
frame. Querying needs no Taichi: voxel keys are packed into one int64 and looked up with a
binary search in the sorted keys of each tile.
"""

from __future__ import annotations

import json
import os
from collections import OrderedDict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tisem.blend import answer_blend
from tisem.io.mapfile import atomic_write, load_map_file, save_map
from tisem.scan import checked_query_points
from tisem.snapshot import MapSnapshot

__all__ = [
    "TILE_VOX",
    "INDEX_NAME",
    "TiledMap",
    "TileIndex",
    "is_tiled_map",
    "tile_ids",
    "split_by_tile",
    "write_tile",
    "write_index",
    "pack_keys",
    "empty_snapshot",
    "concat_snapshots",
]

TILE_VOX = 256  # voxels per tile edge in x and y: 51.2 m at 0.2 m, 8 top cells
INDEX_NAME = "tiles.json"
INDEX_FORMAT = "tisem-tiles"
INDEX_VERSION = 1
_PACK_BITS = 21  # per axis: |key| < 2^20 voxels (+-209 km at 0.2 m)
_PACK_OFFSET = 1 << (_PACK_BITS - 1)


def pack_keys(keys: np.ndarray) -> np.ndarray:
    """(M,) int64, one per (M, 3) voxel key, ordered as the keys' (x, y, z) lexicographic order
    (so a snapshot's sorted keys pack into a sorted array)."""
    k = np.asarray(keys, np.int64) + _PACK_OFFSET
    if len(k) and (k.min() < 0 or k.max() >= 1 << _PACK_BITS):
        raise ValueError(f"voxel keys beyond +-{_PACK_OFFSET} per axis cannot be packed")
    return (k[:, 0] << (2 * _PACK_BITS)) | (k[:, 1] << _PACK_BITS) | k[:, 2]


def tile_ids(keys: np.ndarray, tile_vox: int = TILE_VOX) -> np.ndarray:
    """(M, 2) int64 tile of each voxel key (x and y floor-divided by the tile edge)."""
    return np.floor_divide(np.asarray(keys, np.int64)[:, :2], tile_vox)


def empty_snapshot(num_classes: int, resolution_m: float) -> MapSnapshot:
    return MapSnapshot(
        np.zeros((0, 3), np.int64),
        np.zeros((0, num_classes), np.float32),
        np.zeros(0),
        np.zeros(0, np.float32),
        resolution_m,
    )


def take_rows(snap: MapSnapshot, rows: np.ndarray) -> MapSnapshot:
    """The voxels `rows` (indices or a mask) of `snap`, in that order, with what they keep
    besides their counters (occupancy evidence, class centroids)."""
    return snap.subset(rows)


def concat_snapshots(
    parts: list[MapSnapshot], num_classes: int, resolution_m: float
) -> MapSnapshot:
    """The voxels of every part, sorted by key (the parts must not share a voxel)."""
    parts = [p for p in parts if len(p)]
    if not parts:
        return empty_snapshot(num_classes, resolution_m)
    snap = MapSnapshot(
        np.concatenate([p.keys for p in parts]),
        np.concatenate([p.counts for p in parts]),
        np.concatenate([p.t_last for p in parts]),
        np.concatenate([p.ell_m for p in parts]),
        resolution_m,
    )
    if all(p.occupancy is not None for p in parts):
        snap.occupancy = np.concatenate([p.occupancy for p in parts])
        snap.empty_evidence = parts[0].empty_evidence
    if all(p.centroids is not None for p in parts):
        snap.centroids = np.concatenate([p.centroids for p in parts])
        snap.centroid_ratio = parts[0].centroid_ratio
    return take_rows(snap, MapSnapshot.sort_order(snap.keys))


def split_by_tile(
    snap: MapSnapshot, tile_vox: int = TILE_VOX
) -> Iterator[tuple[tuple[int, int], MapSnapshot]]:
    """((tx, ty), the tile's voxels sorted by key) for every tile `snap` has voxels in."""
    if not len(snap):
        return
    tiles = tile_ids(snap.keys, tile_vox)
    order = np.lexsort((tiles[:, 1], tiles[:, 0]))
    tiles = tiles[order]
    starts = np.flatnonzero(np.r_[True, np.any(tiles[1:] != tiles[:-1], axis=1)])
    ends = np.r_[starts[1:], len(order)]
    for lo, hi in zip(starts, ends):
        part = take_rows(snap, order[lo:hi])
        yield (
            (int(tiles[lo, 0]), int(tiles[lo, 1])),
            take_rows(part, MapSnapshot.sort_order(part.keys)),
        )


def tile_file(tile: tuple[int, int]) -> str:
    return f"tiles/tile_{tile[0]}_{tile[1]}.npz"


def write_tile(
    folder: str | os.PathLike,
    tile: tuple[int, int],
    snap: MapSnapshot,
    mapper_config: dict,
    meta: dict | None = None,
) -> dict:
    """Write one tile's map file under `folder/tiles/`; returns its index entry."""
    rel = tile_file(tile)
    path = Path(folder) / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    save_map(path, snap, mapper_config, dict(meta or {}, tile=list(tile)))
    return {
        "tile": list(tile),
        "file": rel,
        "voxels": len(snap),
        "bytes": path.stat().st_size,
        "t_last_min": float(snap.t_last.min()) if len(snap) else None,
        "t_last_max": float(snap.t_last.max()) if len(snap) else None,
    }


@dataclass
class TileIndex:
    """What tiles.json says: the map's shape and its tiles (entries of `write_tile`)."""

    resolution_m: float
    num_classes: int
    tile_vox: int
    world_frame: str
    mapper_config: dict
    tiles: list[dict]
    meta: dict

    @property
    def voxels(self) -> int:
        return int(sum(t["voxels"] for t in self.tiles))

    def to_dict(self) -> dict:
        return {
            "format": INDEX_FORMAT,
            "format_version": INDEX_VERSION,
            "resolution_m": self.resolution_m,
            "num_classes": self.num_classes,
            "tile_vox": self.tile_vox,
            "world_frame": self.world_frame,
            "voxels": self.voxels,
            "mapper_config": self.mapper_config,
            "meta": self.meta,
            "tiles": sorted(self.tiles, key=lambda t: tuple(t["tile"])),
        }

    @classmethod
    def read(cls, folder: str | os.PathLike) -> TileIndex:
        path = Path(folder) / INDEX_NAME
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise FileNotFoundError(f"{folder}: not a tiled map (no {INDEX_NAME})") from None
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: unreadable tile index: {exc}") from exc
        if data.get("format") != INDEX_FORMAT:
            raise ValueError(f"{path}: not a tisem tile index")
        if int(data.get("format_version", 0)) > INDEX_VERSION:
            raise ValueError(
                f"{path}: tile index version {data['format_version']} is newer "
                f"than this tisem understands ({INDEX_VERSION})"
            )
        return cls(
            float(data["resolution_m"]),
            int(data["num_classes"]),
            int(data["tile_vox"]),
            str(data["world_frame"]),
            dict(data["mapper_config"]),
            list(data["tiles"]),
            dict(data.get("meta") or {}),
        )


def write_index(folder: str | os.PathLike, index: TileIndex) -> Path:
    """tiles.json, atomically: written last, so a folder with an index has all its tiles."""
    path = Path(folder) / INDEX_NAME
    text = json.dumps(index.to_dict(), indent=1).encode()
    atomic_write(path, lambda f: f.write(text))
    return path


def is_tiled_map(path: str | os.PathLike) -> bool:
    return (Path(path) / INDEX_NAME).is_file()


class TiledMap:
    """A tiled map, read lazily: only the index at first, each tile when a query needs it
    (the `cache_tiles` most recently used stay in memory)."""

    def __init__(self, folder: str | os.PathLike, index: TileIndex, cache_tiles: int = 32):
        self.folder = Path(folder)
        self.index = index
        self.cache_tiles = int(cache_tiles)
        self._entries = {tuple(t["tile"]): t for t in index.tiles}
        self._cache: OrderedDict[tuple[int, int], tuple[MapSnapshot, np.ndarray]] = OrderedDict()
        self.tiles_loaded = 0  # tile files read so far (a re-read counts again)

    @classmethod
    def open(cls, folder: str | os.PathLike, cache_tiles: int = 32) -> TiledMap:
        return cls(folder, TileIndex.read(folder), cache_tiles)

    @property
    def resolution_m(self) -> float:
        return self.index.resolution_m

    @property
    def num_classes(self) -> int:
        return self.index.num_classes

    @property
    def world_frame(self) -> str:
        return self.index.world_frame

    @property
    def voxels(self) -> int:
        return self.index.voxels

    def __len__(self) -> int:
        return self.voxels

    @property
    def tile_keys(self) -> list[tuple[int, int]]:
        return sorted(self._entries)

    def entry(self, tile: tuple[int, int]) -> dict | None:
        """The index entry of a tile (None: the map has no voxel there)."""
        return self._entries.get(tuple(tile))

    def tile(self, tile: tuple[int, int]) -> MapSnapshot:
        """The voxels of one tile (empty when the map has none there)."""
        return self._tile(tuple(tile))[0]

    def _tile(self, tile: tuple[int, int]) -> tuple[MapSnapshot, np.ndarray]:
        hit = self._cache.pop(tile, None)
        if hit is None:
            entry = self._entries.get(tile)
            if entry is None:
                snap = empty_snapshot(self.num_classes, self.resolution_m)
            else:
                snap = load_map_file(self.folder / entry["file"])[0]
                self.tiles_loaded += 1
            hit = (snap, pack_keys(snap.keys))
        self._cache[tile] = hit
        while len(self._cache) > self.cache_tiles:
            self._cache.popitem(last=False)
        return hit

    def iter_tiles(self) -> Iterator[tuple[tuple[int, int], MapSnapshot]]:
        for tile in self.tile_keys:
            yield tile, self.tile(tile)

    def query(
        self, points_world: np.ndarray, with_probs: bool = True, blend: bool | None = None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Labels (N,) int32 and probabilities (N, C) float32 of world points, as `Mapper.query`
        gives them: from the voxel each falls in (with its class centroids), and for a point
        whose voxel holds no evidence and is not seen empty, the blend of the voxels within
        `query_radius_m` (tisem.blend), where the map's config says `query_blend: missing`;
        else, and where there is nothing within reach, label 0 and zeros. `blend` False:
        lookups only; True: blend whatever the config says."""
        pts = checked_query_points(points_world)
        n = len(pts)
        labels = np.zeros(n, np.int32)
        probs = np.zeros((n, self.num_classes), np.float32) if with_probs else None
        finite = np.flatnonzero(np.isfinite(pts).all(axis=1))
        if not len(finite):
            return labels, probs
        keys = np.floor(pts[finite] / self.resolution_m).astype(np.int64)
        inside = np.all(np.abs(keys) < _PACK_OFFSET, axis=1)
        finite, keys = finite[inside], keys[inside]
        empty = np.zeros(n, bool)  # points in a voxel seen through (free space)
        for at, voxels in self._voxels_of(keys):
            target = finite[at]
            labels[target] = voxels.point_labels(pts[target])
            empty[target] = voxels.empty()
            if with_probs:
                probs[target] = voxels.probabilities()
        config = self.index.mapper_config
        if blend is None:
            blend = config.get("query_blend", "off") == "missing"
        radius = float(config.get("query_radius_m", 0.0))
        if blend and radius > 0:
            # (from the voxels within reach, whichever tiles hold them)
            todo = finite[(labels[finite] == 0) & ~empty[finite]]
            answer_blend(pts, todo, self.resolution_m, radius, self._posterior_of, labels, probs)
        return labels, probs

    def _posterior_of(self, keys: np.ndarray) -> np.ndarray:
        """(K, C) normalised counters of world voxels `keys`, zeros where the map holds none,
        none with evidence, or empty space."""
        out = np.zeros((len(keys), self.num_classes))
        for at, voxels in self._voxels_of(keys):
            out[at] = voxels.probabilities()
        return out

    def _voxels_of(self, keys: np.ndarray) -> Iterator[tuple[np.ndarray, MapSnapshot]]:
        """Per tile the keys fall in: (the positions in `keys` of those the map holds, their
        voxels in that order). Keys are packed into one int64 and found by a binary search in
        the tile's sorted keys."""
        tiles = tile_ids(keys, self.index.tile_vox)
        for tile in np.unique(tiles, axis=0):
            at = np.flatnonzero(np.all(tiles == tile, axis=1))
            snap, packed = self._tile((int(tile[0]), int(tile[1])))
            if not len(snap):
                continue
            wanted = pack_keys(keys[at])
            pos = np.minimum(np.searchsorted(packed, wanted), len(packed) - 1)
            found = packed[pos] == wanted
            yield at[found], take_rows(snap, pos[found])

    def snapshot(
        self, max_voxels: int | None = None, tiles: Iterable[tuple[int, int]] | None = None
    ) -> MapSnapshot:
        """The map (or the given tiles) as one snapshot; refuses more than `max_voxels`."""
        chosen = self.tile_keys if tiles is None else [tuple(t) for t in tiles]
        total = sum(self._entries[t]["voxels"] for t in chosen if t in self._entries)
        if max_voxels is not None and total > max_voxels:
            raise MemoryError(
                f"{self.folder}: {total:,} voxels do not fit the limit of "
                f"{max_voxels:,}; read it tile by tile (iter_tiles / query)"
            )
        parts = [self.tile(t) for t in chosen]
        return concat_snapshots(parts, self.num_classes, self.resolution_m)
