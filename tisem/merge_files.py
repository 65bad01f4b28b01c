"""`merge_maps`: maps on disk (results folders, map.npz files, tiled maps) into one tiled map.

    result = merge_maps(["results/robot0", "results/robot1/map.npz"], "results/merged")
    result = merge_maps([a, b], out, transforms={1: T_a_b})   # b's frame into a's

The maps must share resolution and label space, and a world frame: a map's frame is what its
file says (`world_frame` in a tiled map's index or a map file's meta), else what the run that
wrote it read (run.json beside it: a SemanticKITTI sequence is its own frame unless its folder
names a shared one, an MCAP recording its map frame, `tisem.logs`). Maps in other frames than
the first are refused unless `transforms` gives the transform into the first map's frame.
The merge goes tile by tile (`tisem.merge.merge_snapshots` per tile), so tiled inputs are never
held whole; the output is a tiled map, and map.npz / map.ply / map_bev.png when it fits.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tisem.config import mapper_config_from_dict
from tisem.io.mapfile import load_map_file, save_map
from tisem.logs import kitti_world_frame
from tisem.merge import check_compatible, merge_snapshots, transform_snapshot
from tisem.snapshot import MapSnapshot
from tisem.tiles import (
    TILE_VOX,
    TiledMap,
    TileIndex,
    is_tiled_map,
    split_by_tile,
    write_index,
    write_tile,
)

log = logging.getLogger(__name__)

__all__ = ["merge_maps", "MergeResult", "map_world_frame", "parse_transform", "write_usual_files"]


@dataclass
class MapInput:
    """One map to merge: a tiled map (read tile by tile) or a snapshot in memory."""

    name: str
    world_frame: str
    mapper_config: dict
    tiled: TiledMap | None = None
    tiles: dict | None = None  # tile -> MapSnapshot, for a map in memory

    @property
    def tau_s(self) -> float:
        return mapper_config_from_dict(self.mapper_config).decay_tau_s

    @property
    def resolution_m(self) -> float:
        return float(self.tiled.resolution_m if self.tiled else self.mapper_config["resolution_m"])

    @property
    def num_classes(self) -> int:
        return int(self.tiled.num_classes if self.tiled else self.mapper_config["num_classes"])

    def tile_keys(self) -> set:
        return set(self.tiled.tile_keys) if self.tiled else set(self.tiles)

    def tile(self, tile) -> MapSnapshot | None:
        if self.tiled is not None:
            return self.tiled.tile(tile) if self.tiled.entry(tile) else None
        return self.tiles.get(tile)


@dataclass
class MergeResult:
    out_dir: Path
    voxels: int
    tiles: int
    inputs: list[dict]
    seconds: float


def _run_json_frame(folder: Path) -> str | None:
    """The world frame of the data a results folder's run.json says was read."""
    path = folder / "run.json"
    if not path.is_file():
        return None
    info = json.loads(path.read_text())
    if info.get("data"):
        return kitti_world_frame(info["data"])
    if info.get("mcap"):
        frame = (info.get("options") or {}).get("map_frame", "map")
        return f"mcap:{Path(info['mcap']).resolve()}#{frame}"
    return None


def map_world_frame(path: str | os.PathLike, meta: dict | None = None) -> str:
    """The world frame of a map on disk (module docstring); `unknown:<path>` when nothing
    says: such a map merges with others only through a transform."""
    path = Path(path)
    if meta and meta.get("world_frame"):
        return str(meta["world_frame"])
    folder = path if path.is_dir() else path.parent
    return _run_json_frame(folder) or f"unknown:{path.resolve()}"


def open_input(path: str | os.PathLike, tile_vox: int) -> MapInput:
    path = Path(path)
    if is_tiled_map(path):
        tiled = TiledMap.open(path, cache_tiles=2)
        return MapInput(str(path), tiled.world_frame, tiled.index.mapper_config, tiled=tiled)
    file = path / "map.npz" if path.is_dir() else path
    if not file.is_file():
        raise FileNotFoundError(
            f"{path}: no map (expected a tiled map folder with tiles.json, "
            f"a results folder with map.npz, or a map.npz)"
        )
    snap, config, meta = load_map_file(file)
    return MapInput(
        str(path), map_world_frame(file, meta), config, tiles=dict(split_by_tile(snap, tile_vox))
    )


def parse_transform(text: str) -> np.ndarray:
    """A 4 x 4 transform from 'tx,ty,tz', 'tx,ty,tz,yaw_deg', 16 or 12 numbers (row-major),
    or a text file holding 12 or 16 numbers."""
    if os.path.isfile(text):
        values = np.array(Path(text).read_text().split(), dtype=np.float64)
    else:
        values = np.array([float(v) for v in text.replace(",", " ").split()])
    T = np.eye(4)
    if values.size in (3, 4):
        T[:3, 3] = values[:3]
        if values.size == 4:
            yaw = np.radians(values[3])
            T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    elif values.size in (12, 16):
        T[:3] = values[:12].reshape(3, 4)
    else:
        raise ValueError(f"a transform is 3, 4, 12 or 16 numbers, got {values.size}: {text!r}")
    return T


def _apply_transform(source: MapInput, T: np.ndarray, tile_vox: int) -> MapInput:
    """The input moved into the reference frame (held in memory: a move changes its tiles)."""
    parts = [source.tile(t) for t in sorted(source.tile_keys())]
    snap = merge_snapshots([p for p in parts if p is not None], source.tau_s) if parts else None
    moved = transform_snapshot(snap, T, source.tau_s) if snap is not None else None
    tiles = dict(split_by_tile(moved, tile_vox)) if moved is not None else {}
    return MapInput(source.name, "", source.mapper_config, tiles=tiles)


def merge_maps(
    inputs: list[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    transforms: dict[int, np.ndarray] | None = None,
    tile_vox: int = TILE_VOX,
    max_merged_voxels: int = 20_000_000,
    progress: bool = False,
) -> MergeResult:
    """Merge the maps `inputs` into the tiled map `out_dir` (module docstring). `transforms`
    maps an input's position (>= 1) to T_first_input: its frame into the first map's.
    `progress`: a bar counting the tiles merged."""
    started = time.perf_counter()
    if len(inputs) < 1:
        raise ValueError("give at least one map to merge")
    transforms = dict(transforms or {})
    if 0 in transforms:
        raise ValueError("the first map is the reference frame: give transforms for the others")
    maps = [open_input(p, tile_vox) for p in inputs]
    check_compatible([(m.name, m.resolution_m, m.num_classes) for m in maps])
    reference = maps[0].world_frame
    for k, m in enumerate(maps[1:], start=1):
        if k in transforms:
            maps[k] = _apply_transform(m, transforms[k], tile_vox)
        elif m.world_frame != reference:
            raise ValueError(
                f"{m.name} is in world frame {m.world_frame!r}, {maps[0].name} in "
                f"{reference!r}: give the transform between them (--transform "
                f"{k}=...)"
            )
    modes = {mapper_config_from_dict(m.mapper_config).mode for m in maps}
    if len(modes) > 1:
        log.warning(
            "merging maps of different modes %s: each decays with its own tau", sorted(modes)
        )
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    entries = []
    tiles = sorted(set().union(*(m.tile_keys() for m in maps)))
    for tile in tqdm(tiles, desc="merging tiles", unit="tile", disable=not progress):
        held = [(m.tile(tile), m.tau_s) for m in maps]
        held = [(s, tau) for s, tau in held if s is not None and len(s)]
        if held:
            merged = merge_snapshots([s for s, _ in held], [tau for _, tau in held])
            entries.append(write_tile(out_dir, tile, merged, maps[0].mapper_config))
    described = [
        {
            "map": str(p),
            "world_frame": m.world_frame or "(transformed)",
            "transform": transforms[k].tolist() if k in transforms else None,
        }
        for k, (p, m) in enumerate(zip(inputs, maps))
    ]
    index = TileIndex(
        maps[0].resolution_m,
        maps[0].num_classes,
        tile_vox,
        reference,
        maps[0].mapper_config,
        entries,
        {"merged_from": described},
    )
    write_index(out_dir, index)
    if index.voxels <= max_merged_voxels:
        write_usual_files(
            out_dir,
            TiledMap.open(out_dir).snapshot(),
            maps[0].mapper_config,
            {"world_frame": reference, "merged_from": described},
        )
    return MergeResult(
        out_dir, index.voxels, len(entries), described, time.perf_counter() - started
    )


def write_usual_files(
    out_dir: str | os.PathLike,
    snap: MapSnapshot,
    mapper_config: dict,
    meta: dict,
    trajectories: list | None = None,
) -> None:
    """map.npz, map.ply and map_bev.png of a merged map that fits in memory."""
    from tisem.io.export import write_ply
    from tisem.viz.bev import render_bev

    out_dir = Path(out_dir)
    save_map(out_dir / "map.npz", snap, mapper_config, meta)
    write_ply(out_dir / "map.ply", snap)
    if len(snap):
        paths = [np.asarray(t, np.float64).reshape(-1, 2) for t in trajectories or [] if len(t)]
        render_bev(
            snap,
            out_dir / "map_bev.png",
            trajectory_xy=np.concatenate(paths) if paths else None,
            title=f"merged tisem map, {len(snap):,} voxels",
        )
