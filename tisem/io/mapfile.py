"""The tisem map file (`map.npz`) and checkpoint files, written atomically.

A map file holds everything needed to rebuild the map: the snapshot arrays (keys, counts,
t_last, ell_m, resolution_m), the class table it was built with (names, colours, raw ids),
the mapper config (YAML text) and free metadata (JSON text: scan index, time of the last
scan, origin...). Text goes in as 0-d unicode arrays so the file loads with
`allow_pickle=False`: opening a map never executes code from the file.

Writes are atomic: the file is written under a temporary name in the same folder, fsync'ed,
then `os.replace`d over the target. A crash or kill mid-save leaves either the old file or
the new one, never a torn one, which is what makes `--checkpoint-every N` safe to rely on.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np
import yaml

from tisem.class_centroids import centroid_problem
from tisem.config import MapperConfig
from tisem.labels import CLASS_COLORS_RGB, CLASS_NAMES, LEARNING_MAP_INV
from tisem.snapshot import MapSnapshot

__all__ = [
    "MapFileError",
    "atomic_write",
    "save_map",
    "load_map_file",
    "save_checkpoint_file",
    "load_checkpoint_file",
    "remove_stale_temp_files",
    "CHECKPOINT_NAME",
    "FORMAT_NAME",
    "FORMAT_VERSION",
]

FORMAT_NAME = "tisem-map"
FORMAT_VERSION = 1
CHECKPOINT_NAME = "checkpoint.npz"

# every array a valid file must hold (the class table is informative, see load_map_file)
_REQUIRED = (
    "format",
    "format_version",
    "keys",
    "counts",
    "t_last",
    "ell_m",
    "resolution_m",
    "mapper_config_yaml",
    "meta_json",
)


# mkstemp creates 0600 files; give the final file the mode a plain open() would have. Read
# once at import: os.umask can only be read by setting it, which is racy once threads run.
_UMASK = os.umask(0)
os.umask(_UMASK)


class MapFileError(ValueError):
    """A file is not a tisem map, or is damaged (the message names the file)."""


def _json_default(obj):
    # meta often carries numpy scalars / arrays (scan index, origin); store them as plain JSON
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"meta value of type {type(obj).__name__} is not JSON-serialisable")


def _config_dict(mapper_config: MapperConfig | dict | None) -> dict:
    if dataclasses.is_dataclass(mapper_config):
        return dataclasses.asdict(mapper_config)
    return dict(mapper_config or {})


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], object]) -> None:
    """Call `write(file_object)` on a temp file next to `path`, fsync, then rename onto `path`.

    The temp file lives in the target's folder because `os.replace` is only atomic within one
    file system. On any failure the temp file is removed and `path` is left untouched.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            if hasattr(os, "fchmod"):
                os.fchmod(f.fileno(), 0o666 & ~_UMASK)
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    # make the rename itself durable (POSIX); not possible / not needed on every platform
    try:
        dir_fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)


def _class_table_arrays(num_classes: int) -> dict:
    """The class table for `num_classes` counters: SemanticKITTI's, cut or padded so it always
    has one row per counter (extra classes get generic names, grey and raw id 0)."""
    known = min(num_classes, len(CLASS_NAMES))
    extra = num_classes - known
    return {
        "class_names": np.array(
            list(CLASS_NAMES[:known]) + [f"class-{i}" for i in range(known, num_classes)]
        ),
        "class_colors_rgb": np.concatenate(
            [CLASS_COLORS_RGB[:known], np.full((extra, 3), 128, np.uint8)]
        ),
        "class_raw_ids": np.concatenate([LEARNING_MAP_INV[:known], np.zeros(extra, np.uint32)]),
    }


def save_map(
    path: str | os.PathLike,
    snapshot: MapSnapshot,
    mapper_config: MapperConfig | dict,
    meta: dict | None = None,
    compress: bool = True,
) -> Path:
    """Write `snapshot` + config + meta to `path` (an .npz), atomically. Returns the path.

    `mapper_config` is a dict or a `MapperConfig`. `compress=False` trades size for speed
    (the counters are mostly zeros, so compression usually shrinks them several-fold).
    """
    path = Path(path)
    arrays = {
        "format": np.array(FORMAT_NAME),
        "format_version": np.array(FORMAT_VERSION, dtype=np.int64),
        "keys": np.asarray(snapshot.keys, dtype=np.int64),
        "counts": np.asarray(snapshot.counts, dtype=np.float32),
        "t_last": np.asarray(snapshot.t_last, dtype=np.float64),
        "ell_m": np.asarray(snapshot.ell_m, dtype=np.float32),
        "resolution_m": np.array(snapshot.resolution_m, dtype=np.float64),
        **_class_table_arrays(np.shape(snapshot.counts)[1]),
        "mapper_config_yaml": np.array(
            yaml.safe_dump(_config_dict(mapper_config), sort_keys=False)
        ),
        "meta_json": np.array(json.dumps(meta or {}, default=_json_default, sort_keys=True)),
    }
    if snapshot.occupancy is not None:  # free space: the occupancy evidence, optional
        arrays["occupancy"] = np.asarray(snapshot.occupancy, dtype=np.float32)
        arrays["empty_evidence"] = np.array(snapshot.empty_evidence, dtype=np.float64)
    if snapshot.centroids is not None:  # class centroids, optional
        arrays["centroids"] = np.asarray(snapshot.centroids, dtype=np.float32)
        arrays["centroid_ratio"] = np.array(snapshot.centroid_ratio, dtype=np.float64)
    savez = np.savez_compressed if compress else np.savez
    atomic_write(path, lambda f: savez(f, **arrays))
    return path


def load_map_file(path: str | os.PathLike) -> tuple[MapSnapshot, dict, dict]:
    """Read a map file written by `save_map`: (snapshot, mapper_config dict, meta dict).

    Raises FileNotFoundError when the file is missing and `MapFileError` (naming the file and
    the problem) when it is not a tisem map, is truncated / corrupt, or its arrays disagree.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: map file not found")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04":
        # checked before np.load, which would take any other file for a pickle or .npy
        raise MapFileError(
            f"{path}: not a tisem map file (not an npz archive: starts with {magic!r})"
        )
    try:
        # read everything inside the try: npz members are decompressed (and CRC-checked) lazily
        with np.load(path, allow_pickle=False) as npz:
            missing = [k for k in _REQUIRED if k not in npz.files]
            if "format" not in npz.files or str(npz["format"]) != FORMAT_NAME:
                raise MapFileError(
                    f"{path}: not a tisem map file (no '{FORMAT_NAME}' marker; "
                    f"arrays present: {', '.join(npz.files) or 'none'})"
                )
            if missing:
                raise MapFileError(
                    f"{path}: damaged tisem map file, missing arrays: {', '.join(missing)}"
                )
            version = int(npz["format_version"])
            data = {k: npz[k] for k in _REQUIRED}
            # free space and class centroids, when the map had them
            for k in ("occupancy", "empty_evidence", "centroids", "centroid_ratio"):
                if k in npz.files:
                    data[k] = npz[k]
            class_names = npz["class_names"] if "class_names" in npz.files else None
    except MapFileError:
        raise
    except (
        zipfile.BadZipFile,
        zlib.error,
        EOFError,
        OSError,
        ValueError,
        KeyError,
        TypeError,
    ) as exc:
        raise MapFileError(
            f"{path}: not a readable tisem map file (truncated or damaged?): "
            f"{type(exc).__name__}: {exc}"
        ) from exc
    if version > FORMAT_VERSION:
        raise MapFileError(
            f"{path}: map file format version {version} is newer than this "
            f"tisem understands ({FORMAT_VERSION})"
        )

    keys, counts, t_last, ell_m = data["keys"], data["counts"], data["t_last"], data["ell_m"]
    m = keys.shape[0] if keys.ndim == 2 else -1
    if (
        keys.ndim != 2
        or keys.shape[1] != 3
        or counts.ndim != 2
        or counts.shape[0] != m
        or t_last.shape != (m,)
        or ell_m.shape != (m,)
    ):
        raise MapFileError(
            f"{path}: damaged tisem map file, inconsistent array shapes: keys "
            f"{keys.shape}, counts {counts.shape}, t_last {t_last.shape}, "
            f"ell_m {ell_m.shape}"
        )
    if class_names is not None and class_names.shape != (counts.shape[1],):
        raise MapFileError(
            f"{path}: damaged tisem map file, {counts.shape[1]} class counters "
            f"but a class table of {class_names.size} names"
        )
    try:
        config = yaml.safe_load(str(data["mapper_config_yaml"])) or {}
        meta = json.loads(str(data["meta_json"]))
    except (yaml.YAMLError, json.JSONDecodeError) as exc:
        raise MapFileError(
            f"{path}: damaged tisem map file, unreadable config/meta text: "
            f"{' '.join(str(exc).split())}"
        ) from None
    if not isinstance(config, dict) or not isinstance(meta, dict):
        raise MapFileError(
            f"{path}: damaged tisem map file, its mapper config and meta must be mappings"
        )
    _check_values(path, keys, counts, t_last, ell_m, data["resolution_m"])
    snapshot = MapSnapshot(
        keys=keys.astype(np.int64, copy=False),
        counts=counts.astype(np.float32, copy=False),
        t_last=t_last.astype(np.float64, copy=False),
        ell_m=ell_m.astype(np.float32, copy=False),
        resolution_m=float(data["resolution_m"]),
    )
    if "occupancy" in data:
        occupancy = np.asarray(data["occupancy"], np.float32)
        if occupancy.shape != (m,) or not np.isfinite(occupancy).all():
            raise MapFileError(
                f"{path}: damaged tisem map file, occupancy must be {m} finite "
                f"values, got {occupancy.shape}"
            )
        snapshot.occupancy = occupancy
        snapshot.empty_evidence = float(data["empty_evidence"])
    if "centroids" in data:
        raw, ratio = data["centroids"], data.get("centroid_ratio", np.array(np.nan))
        if raw.dtype.kind not in "iuf" or ratio.dtype.kind not in "iuf" or ratio.ndim:
            raise MapFileError(
                f"{path}: damaged tisem map file, centroids and centroid_ratio must be numbers"
            )
        centroids, ratio = np.asarray(raw, np.float32), float(ratio)
        problem = centroid_problem(centroids, m, counts.shape[1])
        if problem is None and not 0.0 <= ratio <= 1.0:
            problem = f"centroid_ratio must lie in [0, 1], got {ratio!r}"
        if problem is not None:
            raise MapFileError(f"{path}: damaged tisem map file, {problem}")
        snapshot.centroids = centroids
        snapshot.centroid_ratio = ratio
    return snapshot, config, meta


def _check_values(path: Path, keys, counts, t_last, ell_m, resolution_m) -> None:
    """What no map can hold: MapFileError naming the array and the value (the arrays' CRCs
    can be right and their contents still not a map, e.g. a file written by other code)."""

    def bad(what: str) -> MapFileError:
        return MapFileError(f"{path}: damaged tisem map file, {what}")

    if not np.issubdtype(keys.dtype, np.integer):
        raise bad(f"voxel keys of type {keys.dtype}, not integers")
    for name, a in (("counts", counts), ("t_last", t_last), ("ell_m", ell_m)):
        if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
            raise bad(f"{name} of type {a.dtype}, not numbers")
        if a.size and not np.isfinite(a).all():
            raise bad(f"{name} holds NaN/inf values ({int((~np.isfinite(a)).sum())} of them)")
    for name, a in (("counts", counts), ("ell_m", ell_m)):
        if a.size and a.min() < 0:
            raise bad(f"{name} holds negative values (down to {float(a.min()):g})")
    try:
        res = float(resolution_m)
    except (TypeError, ValueError):
        raise bad(f"resolution_m {resolution_m!r} is not a number") from None
    if not np.isfinite(res) or res <= 0:
        raise bad(f"resolution_m {res!r} is not a voxel size > 0")


def remove_stale_temp_files(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files (`.<name>.*.tmp`, `atomic_write`'s) that a save killed
    before its rename left beside `path`; returns what was removed. Only for files one
    process writes at a time (a checkpoint): a live save's file would go too."""
    path = Path(path)
    removed = []
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        try:
            tmp.unlink()
            removed.append(tmp)
        except OSError:
            pass  # not ours to fight over: the next save tries again
    return removed


def save_checkpoint_file(
    directory: str | os.PathLike,
    snapshot: MapSnapshot,
    mapper_config: MapperConfig | dict,
    meta: dict | None = None,
) -> Path:
    """Write the map file `directory/checkpoint.npz` atomically (uncompressed: checkpoints are
    frequent). `tisem.checkpoint.save_checkpoint` fills `meta` with a run's progress.

    The fixed name means a resumed run always finds the latest one, and the atomic replace
    means the previous checkpoint survives a crash during this one.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    remove_stale_temp_files(directory / CHECKPOINT_NAME)
    return save_map(directory / CHECKPOINT_NAME, snapshot, mapper_config, meta, compress=False)


def load_checkpoint_file(directory: str | os.PathLike) -> tuple[MapSnapshot, dict, dict]:
    """Read the map file `directory/checkpoint.npz`: (snapshot, mapper_config dict, meta dict),
    as `load_map_file` does (`tisem.checkpoint.load_checkpoint` gives a `Checkpoint`)."""
    path = Path(directory) / CHECKPOINT_NAME
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no checkpoint to resume from (expected {CHECKPOINT_NAME} in {directory})"
        )
    return load_map_file(path)
