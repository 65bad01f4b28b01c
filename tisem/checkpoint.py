"""Checkpoints, resume and `load_map`.

A checkpoint is a map file (`tisem.io.mapfile`) named `<results>/checkpoint/checkpoint.npz`,
written atomically, whose meta holds everything a run needs to go on exactly where it stopped:

    meta = {"kind": "checkpoint",
            "last_index": 41,                  # Scan.index of the last integrated scan
            "mapper_state": mapper.state(),    # origin, t0, window centre, scan count
            "run_config": {...},               # the resolved RunConfig (to_dict)
            "progress": {"online": C x C, "input": C x C,    # RunProgress.to_dict(), less
                         "seconds": [...], "skipped": [...],  # last_index, which is kept at
                         "trajectory": [[x, y, z], ...],      # the top for a quick look
                         "dropped": {...}},
            "source": {...}}                   # what run.json says (data folder, sequence, ...)

The mapper config itself is the file's `mapper_config_yaml`, the map its snapshot arrays.

    ckpt = load_checkpoint("results/run")          # a results folder, its checkpoint/ or the file
    mapper = ckpt.build_mapper()                   # Mapper(config) + restore(snapshot, state)
    MappingRun.resume(seq, ckpt).run()             # tisem.run: continue the run

    mapper = tisem.load_map("results/run/map.npz") # any map file or checkpoint, ready to query
    labels, probs = mapper.query(points_world)
    tiled = tisem.load_map("results/fleet/maps/x")  # a tiled map: a TiledMap, read lazily
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tisem.config import (
    ConfigError,
    MapperConfig,
    RunConfig,
    mapper_config_from_dict,
    run_config_from_dict,
    to_dict,
)
from tisem.io import mapfile
from tisem.progress import RunProgress
from tisem.snapshot import MapSnapshot

if TYPE_CHECKING:  # (importing the mapper starts Taichi)
    from tisem.mapper import Mapper
    from tisem.tiles import TiledMap

log = logging.getLogger(__name__)

__all__ = [
    "CHECKPOINT_DIR",
    "Checkpoint",
    "checkpoint_file",
    "load_checkpoint",
    "save_checkpoint",
    "open_checkpoint",
    "load_map",
    "mapper_from_file",
]

CHECKPOINT_DIR = "checkpoint"  # <results>/checkpoint/checkpoint.npz
MAP_NAME = "map.npz"


def checkpoint_file(path: str | os.PathLike) -> Path:
    """The checkpoint file of `path`: a results folder, its checkpoint folder, or the file."""
    path = Path(path)
    if path.is_file():
        return path
    for cand in (path / CHECKPOINT_DIR / mapfile.CHECKPOINT_NAME, path / mapfile.CHECKPOINT_NAME):
        if cand.is_file():
            return cand
    raise FileNotFoundError(
        f"{path}: no checkpoint to resume from (looked for "
        f"{CHECKPOINT_DIR}/{mapfile.CHECKPOINT_NAME} and "
        f"{mapfile.CHECKPOINT_NAME} in it)"
    )


def _map_file(path: str | os.PathLike) -> Path:
    """A map file to load: the file itself, or a results folder's map.npz (else checkpoint)."""
    path = Path(path)
    if path.is_file():
        return path
    if (path / MAP_NAME).is_file():
        return path / MAP_NAME
    if path.is_dir():
        try:
            return checkpoint_file(path)
        except FileNotFoundError:
            pass
    raise FileNotFoundError(
        f"{path}: no map file (expected a .npz, or a folder with {MAP_NAME} "
        f"or {CHECKPOINT_DIR}/{mapfile.CHECKPOINT_NAME})"
    )


def _state_from_snapshot(snapshot: MapSnapshot) -> dict:
    """A mapper state for a map file written without one: origin at the block-aligned median
    key (keeps relative keys small), t0 at the oldest update, window at the origin."""
    if len(snapshot) == 0:
        return {"origin_vox": None}
    # imported here: the rule comes from the SNode layout, and `import tisem; tisem.load_map`
    # must not start Taichi
    from tisem.geometry import block_aligned_origin

    origin = block_aligned_origin(np.median(snapshot.keys, axis=0).astype(np.int64))
    return {
        "origin_vox": origin.tolist(),
        "t0": float(snapshot.t_last.min()),
        "center_vox": [0, 0, 0],
        "scans": 0,
        "last_stamp_s": None,
    }


@dataclass
class Checkpoint:
    """A loaded checkpoint (or map file): the map, its mapper config and the run's meta."""

    path: Path
    snapshot: MapSnapshot
    mapper_config: dict
    meta: dict

    @property
    def last_index(self) -> int | None:
        """`Scan.index` of the last scan integrated before the checkpoint (None: unknown)."""
        v = self.meta.get("last_index")
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
            raise mapfile.MapFileError(
                f"{self.path}: last_index {v!r} is not a scan number (an integer >= 0)"
            )
        return v

    @property
    def mapper_state(self) -> dict:
        # checkpoints nest the state; map.npz files (outputs.write_map_files) store it as meta
        state = self.meta.get("mapper_state", self.meta)
        if not isinstance(state, dict):
            raise mapfile.MapFileError(
                f"{self.path}: the mapper state is not a mapping: {state!r}"[:200]
            )
        if state.get("origin_vox") is None and len(self.snapshot):
            log.warning("%s: no mapper state stored; rebuilding one from the voxels", self.path)
            return _state_from_snapshot(self.snapshot)
        return state

    @property
    def results_dir(self) -> Path:
        """The results folder the checkpoint belongs to (`<results>/checkpoint/<file>`)."""
        folder = self.path.parent
        return folder.parent if folder.name == CHECKPOINT_DIR else folder

    @property
    def source(self) -> dict:
        return dict(self.meta.get("source") or {})

    def config(self) -> MapperConfig:
        """The `MapperConfig` the map was built with. Its store_dir, a folder on the machine
        that wrote the file, is kept only where that folder exists here."""
        data = dict(self.mapper_config)
        store_dir = data.get("store_dir")
        if store_dir is not None and not (isinstance(store_dir, str) and os.path.isdir(store_dir)):
            log.info(
                "%s: its store_dir %r is not a folder here; the store spills to the "
                "system's temp folder",
                self.path,
                store_dir,
            )
            data["store_dir"] = None
        try:
            return mapper_config_from_dict(data, f"{self.path} mapper config")
        except ConfigError as exc:
            raise mapfile.MapFileError(str(exc)) from None

    def run_config(self) -> RunConfig:
        """The resolved `RunConfig` of the run (only the mapper part for a bare map file)."""
        data = self.meta.get("run_config")
        mapper = self.config()
        if not data:
            return RunConfig(mapper=mapper)
        if not isinstance(data, dict):
            raise mapfile.MapFileError(f"{self.path}: run_config is not a mapping")
        try:
            cfg = run_config_from_dict(
                {k: v for k, v in data.items() if k != "mapper"}, f"{self.path} run_config"
            )
        except ConfigError as exc:
            raise mapfile.MapFileError(str(exc)) from None
        cfg.mapper = mapper
        return cfg

    def check(self) -> None:
        """Refuse (MapFileError, one line) a file whose parts do not fit together: a mapper
        config that is not valid, voxels of another size or class count than it says, a
        mapper state that is not one, voxels beyond the map's key range, a progress that is
        not one a run can have saved."""
        cfg = self.config()
        snap = self.snapshot
        if abs(snap.resolution_m - cfg.resolution_m) > 1e-9 * cfg.resolution_m:
            raise mapfile.MapFileError(
                f"{self.path}: its voxels are {snap.resolution_m:g} m but its mapper config "
                f"says resolution_m = {cfg.resolution_m:g}"
            )
        if snap.counts.shape[1] != cfg.num_classes:
            raise mapfile.MapFileError(
                f"{self.path}: its voxels have {snap.counts.shape[1]} class counters but its "
                f"mapper config says num_classes = {cfg.num_classes}"
            )
        _check_state(self.path, self.mapper_state, snap)
        self.run_config()
        self.progress(cfg.num_classes)
        _ = self.last_index  # a property that refuses a value no run wrote

    def build_mapper(self, profile: bool = False, store_dir: str | None = None) -> Mapper:
        """A fresh `Mapper(config)` restored to this checkpoint's map and state. `store_dir`:
        where its store spills (`MapperConfig.store_dir`; not the saved one, a folder on the
        machine that wrote the file)."""
        from tisem.backend import ensure_initialized
        from tisem.mapper import Mapper

        ensure_initialized()
        mapper = Mapper(dataclasses.replace(self.config(), store_dir=store_dir), profile=profile)
        mapper.restore(self.snapshot, self.mapper_state)
        return mapper

    # ------------------------------------------------------------------ the run's progress
    def check_run_config(self, cfg: RunConfig) -> None:
        """Refuse to resume with a different mapper config; warn about other differences."""
        # where the store spills is a place on this machine, not part of the map
        mine, theirs = (
            {k: v for k, v in to_dict(c).items() if k != "store_dir"}
            for c in (self.config(), cfg.mapper)
        )
        diff = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
        if diff:
            listed = ", ".join(f"{k}: {mine.get(k)!r} vs {theirs.get(k)!r}" for k in diff)
            raise ValueError(
                f"{self.path}: the checkpoint was made with a different mapper "
                f"config ({listed}); resume with Checkpoint.run_config()"
            )
        stored = self.meta.get("run_config") or {}
        now = to_dict(cfg)
        other = sorted(k for k in stored if k != "mapper" and stored[k] != now.get(k))
        if other:
            log.warning(
                "resuming %s with a different run config: %s",
                self.path,
                ", ".join(f"{k}: {stored[k]!r} -> {now.get(k)!r}" for k in other),
            )

    def progress(self, num_classes: int) -> RunProgress:
        """The run's progress when the checkpoint was written (empty for a bare map file)."""
        saved = dict(self.meta.get("progress") or {}, last_index=self.last_index)
        try:
            return RunProgress.from_dict(saved, num_classes)
        except (ValueError, TypeError) as exc:
            raise mapfile.MapFileError(f"{self.path}: {exc}") from None


def _check_state(path: Path, state: dict, snapshot: MapSnapshot) -> None:
    """A mapper state (`Mapper.state()`) that can be restored, and voxels within its keys'
    range around the origin; MapFileError otherwise."""
    from tisem.store_segments import KEY_LIMIT  # (imports the layout, and with it taichi)

    def bad(what: str) -> mapfile.MapFileError:
        return mapfile.MapFileError(f"{path}: the mapper state is not one a map can have: {what}")

    def voxel(name: str, optional: bool) -> np.ndarray | None:
        v = state.get(name)
        if v is None and optional:
            return None
        if (
            not isinstance(v, list)
            or len(v) != 3
            or not all(isinstance(x, int) and not isinstance(x, bool) for x in v)
        ):
            raise bad(f"{name} {v!r} is not three integers")
        return np.asarray(v, np.int64)

    if not isinstance(state, dict):
        raise bad(f"{state!r} is not a mapping")
    if state.get("origin_vox") is None:
        if len(snapshot):
            raise bad("no origin_vox for a map that has voxels")
        return
    origin = voxel("origin_vox", optional=False)
    center = voxel("center_vox", optional=True)
    for name in ("t0", "last_stamp_s"):
        v = state.get(name)
        if (v is not None or name == "t0") and (
            isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v)
        ):
            raise bad(f"{name} {v!r} is not a finite time")
    scans = state.get("scans", 0)
    if isinstance(scans, bool) or not isinstance(scans, int) or scans < 0:
        raise bad(f"scans {scans!r} is not a count")
    if np.abs(origin).max() > 2**62 or (center is not None and np.abs(center).max() > KEY_LIMIT):
        raise bad(
            f"origin_vox {origin.tolist()} / center_vox {state.get('center_vox')} are out of range"
        )
    if len(snapshot):
        # in float64: int64 keys near their limits would wrap around
        reach = float(np.abs(snapshot.keys.astype(np.float64) - origin).max())
        if reach > KEY_LIMIT:
            raise mapfile.MapFileError(
                f"{path}: voxel keys reach {reach:,.0f} voxels from the map origin; a map holds "
                f"at most {KEY_LIMIT:,}"
            )


def load_checkpoint(path: str | os.PathLike) -> Checkpoint:
    """Read a checkpoint: `path` is a results folder, its checkpoint folder or the file.
    A file whose parts do not fit together is refused (`Checkpoint.check`, MapFileError)."""
    file = checkpoint_file(path)
    snapshot, config, meta = mapfile.load_map_file(file)
    ckpt = Checkpoint(file, snapshot, config, meta)
    ckpt.check()
    return ckpt


def save_checkpoint(
    directory: str | os.PathLike,
    mapper: Mapper,
    progress: RunProgress | None = None,
    *,
    run_config: RunConfig | None = None,
    source: dict | None = None,
) -> Path:
    """Save `mapper` (snapshot + state) and the run's `progress` to `directory/checkpoint.npz`.

    Atomic (write, fsync, rename): a crash mid-save leaves the previous checkpoint intact.
    """
    saved = (progress or RunProgress.start(mapper.C)).to_dict()
    meta = {
        "kind": "checkpoint",
        "last_index": saved.pop("last_index"),
        "mapper_state": mapper.state(),
        "run_config": to_dict(run_config) if run_config is not None else None,
        "progress": saved,
        "source": dict(source or {}),
    }
    return mapfile.save_checkpoint_file(directory, mapper.snapshot(), to_dict(mapper.config), meta)


def open_checkpoint(resume: Checkpoint | str | os.PathLike) -> Checkpoint:
    """A `Checkpoint` as given, or loaded from a path (a results folder, its checkpoint folder
    or the file)."""
    return resume if isinstance(resume, Checkpoint) else load_checkpoint(resume)


def mapper_from_file(path: str | os.PathLike) -> tuple[Mapper, Checkpoint]:
    """(Mapper, Checkpoint) for a map file / checkpoint / results folder."""
    file = _map_file(path)
    snapshot, config, meta = mapfile.load_map_file(file)
    ckpt = Checkpoint(file, snapshot, config, meta)
    ckpt.check()
    return ckpt.build_mapper(), ckpt


def load_map(path: str | os.PathLike) -> Mapper | TiledMap:
    """A map ready to query without running the sequence again:
    `load_map(path).query(points) -> labels, probs`.

    A tiled map (a folder with tiles.json: what `fleet` and `merge_maps` write) comes back as
    a `tisem.tiles.TiledMap`, read lazily: only the index now, each tile when a query first
    needs it (`snapshot()` gives the whole map when it fits). A `map.npz`, a checkpoint or a
    results folder comes back as a ready `Mapper`; that initialises Taichi on the CPU when
    nothing has initialised it yet. tisem holds one map per Taichi runtime: in a process that
    already has a map, call `tisem.init_taichi()` first (the old map becomes unusable), or
    `Mapper()` refuses with a RuntimeError.
    """
    from tisem.tiles import TiledMap, is_tiled_map

    if is_tiled_map(path):
        return TiledMap.open(path)
    return mapper_from_file(path)[0]
