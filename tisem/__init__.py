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
import importlib.util
import sys
from pathlib import Path

__version__ = "0.1.0"


def _kernels_of_checkout() -> None:
    """Installed, the kernels are the subpackage tisem/kernels (the build maps the repository's
    top-level kernels/ there). Run from a checkout (PYTHONPATH, or any import path that finds
    this folder directly), tisem/ has no kernels/ beside its modules: `tisem.kernels` is then
    the checkout's kernels/ folder. Every module imports the kernels as `tisem.kernels` only,
    so a checkout and an installed copy load each kernel module (and its Taichi fields) once,
    under one name."""
    package = Path(__file__).resolve().parent
    checkout = package.parent / "kernels" / "__init__.py"
    if (package / "kernels").is_dir() or "tisem.kernels" in sys.modules or not checkout.is_file():
        return
    spec = importlib.util.spec_from_file_location(
        "tisem.kernels", checkout, submodule_search_locations=[str(checkout.parent)]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["tisem.kernels"] = module
    spec.loader.exec_module(module)
    globals()["kernels"] = module  # what the import system does for a subpackage


_kernels_of_checkout()

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
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
