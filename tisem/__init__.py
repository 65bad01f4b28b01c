"""tisem: 3D semantic maps from labelled LiDAR scans, on Taichi sparse fields.

    import tisem
    mapper = tisem.Mapper(tisem.MapperConfig(mode="st"))
    mapper.integrate(scan)                               # a tisem.Scan
    labels, probs = tisem.load_map("results/run/map.npz").query(points_world)

The names below are imported on first use, so `import tisem` stays cheap (no Taichi until a
mapper, `load_map` or `init_taichi` is needed).
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "Mapper": "tisem.mapper",
    "MapperConfig": "tisem.config",
    "RunConfig": "tisem.config",
    "load_config": "tisem.config",
    "Scan": "tisem.scan",
    "MapSnapshot": "tisem.snapshot",
    "load_map": "tisem.checkpoint",
    "merge_maps": "tisem.merge_files",
    "init_taichi": "tisem.backend",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'tisem' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value   # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
