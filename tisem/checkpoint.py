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
"""
from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tisem.config import MapperConfig, RunConfig, _apply, mapper_config_from_dict, to_dict
from tisem.io import mapfile
from tisem.progress import RunProgress
from tisem.snapshot import MapSnapshot

if TYPE_CHECKING:                      # (importing the mapper starts Taichi)
    from tisem.mapper import Mapper

log = logging.getLogger(__name__)

__all__ = ["CHECKPOINT_DIR", "Checkpoint", "checkpoint_file", "load_checkpoint",
           "save_checkpoint", "open_checkpoint", "load_map", "mapper_from_file"]

CHECKPOINT_DIR = "checkpoint"          # <results>/checkpoint/checkpoint.npz
MAP_NAME = "map.npz"


def checkpoint_file(path: str | os.PathLike) -> Path:
    """The checkpoint file of `path`: a results folder, its checkpoint folder, or the file."""
    path = Path(path)
    if path.is_file():
        return path
    for cand in (path / CHECKPOINT_DIR / mapfile.CHECKPOINT_NAME, path / mapfile.CHECKPOINT_NAME):
        if cand.is_file():
            return cand
    raise FileNotFoundError(f"{path}: no checkpoint to resume from (looked for "
                            f"{CHECKPOINT_DIR}/{mapfile.CHECKPOINT_NAME} and "
                            f"{mapfile.CHECKPOINT_NAME} in it)")


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
    raise FileNotFoundError(f"{path}: no map file (expected a .npz, or a folder with {MAP_NAME} "
                            f"or {CHECKPOINT_DIR}/{mapfile.CHECKPOINT_NAME})")


def _state_from_snapshot(snapshot: MapSnapshot) -> dict:
    """A mapper state for a map file written without one: origin at the block-aligned median
    key (keeps relative keys small), t0 at the oldest update, window at the origin."""
    if len(snapshot) == 0:
        return {"origin_vox": None}
    # imported here: the rule comes from the SNode layout, and `import tisem; tisem.load_map`
    # must not start Taichi
    from tisem.geometry import block_aligned_origin
    origin = block_aligned_origin(np.median(snapshot.keys, axis=0).astype(np.int64))
    return {"origin_vox": origin.tolist(), "t0": float(snapshot.t_last.min()),
            "center_vox": [0, 0, 0], "scans": 0, "last_stamp_s": None}


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
        return None if v is None else int(v)

    @property
    def mapper_state(self) -> dict:
        # checkpoints nest the state; map.npz files (outputs.write_map_files) store it as meta
        state = self.meta.get("mapper_state", self.meta)
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
        """The `MapperConfig` the map was built with."""
        return mapper_config_from_dict(self.mapper_config)

    def run_config(self) -> RunConfig:
        """The resolved `RunConfig` of the run (only the mapper part for a bare map file)."""
        cfg = RunConfig()
        data = self.meta.get("run_config")
        if data:
            _apply(cfg, data, f"{self.path} run_config")
        cfg.mapper = self.config()
        return cfg

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
        mine, theirs = ({k: v for k, v in to_dict(c).items() if k != "store_dir"}
                        for c in (self.config(), cfg.mapper))
        diff = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
        if diff:
            listed = ", ".join(f"{k}: {mine.get(k)!r} vs {theirs.get(k)!r}" for k in diff)
            raise ValueError(f"{self.path}: the checkpoint was made with a different mapper "
                             f"config ({listed}); resume with Checkpoint.run_config()")
        stored = self.meta.get("run_config") or {}
        now = to_dict(cfg)
        other = sorted(k for k in stored if k != "mapper" and stored[k] != now.get(k))
        if other:
            log.warning("resuming %s with a different run config: %s", self.path,
                        ", ".join(f"{k}: {stored[k]!r} -> {now.get(k)!r}" for k in other))

    def progress(self, num_classes: int) -> RunProgress:
        """The run's progress when the checkpoint was written (empty for a bare map file)."""
        saved = dict(self.meta.get("progress") or {}, last_index=self.last_index)
        try:
            return RunProgress.from_dict(saved, num_classes)
        except (ValueError, TypeError) as exc:
            raise mapfile.MapFileError(f"{self.path}: {exc}") from None


def load_checkpoint(path: str | os.PathLike) -> Checkpoint:
    """Read a checkpoint: `path` is a results folder, its checkpoint folder or the file."""
    file = checkpoint_file(path)
    snapshot, config, meta = mapfile.load_map_file(file)
    return Checkpoint(file, snapshot, config, meta)


def save_checkpoint(directory: str | os.PathLike, mapper: Mapper,
                    progress: RunProgress | None = None, *,
                    run_config: RunConfig | None = None, source: dict | None = None) -> Path:
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
    return mapfile.save_checkpoint_file(directory, mapper.snapshot(), to_dict(mapper.config),
                                        meta)


def open_checkpoint(resume: Checkpoint | str | os.PathLike) -> Checkpoint:
    """A `Checkpoint` as given, or loaded from a path (a results folder, its checkpoint folder
    or the file)."""
    return resume if isinstance(resume, Checkpoint) else load_checkpoint(resume)


def mapper_from_file(path: str | os.PathLike) -> tuple[Mapper, Checkpoint]:
    """(Mapper, Checkpoint) for a map file / checkpoint / results folder."""
    file = _map_file(path)
    snapshot, config, meta = mapfile.load_map_file(file)
    ckpt = Checkpoint(file, snapshot, config, meta)
    return ckpt.build_mapper(), ckpt


def load_map(path: str | os.PathLike) -> Mapper:
    """A ready `Mapper` from a `map.npz` (or a checkpoint, or a results folder): query it with
    `load_map(path).query(points) -> labels, probs` without running the sequence again.

    Initialises Taichi on the CPU when nothing has initialised it yet. tisem holds one map per
    Taichi runtime: in a process that already has a map, call `tisem.init_taichi()` first
    (the old map becomes unusable), or `Mapper()` refuses with a RuntimeError.
    """
    return mapper_from_file(path)[0]
