"""The optional parts of tisem and the extra that installs each one.

A plain `pip install tisem` maps SemanticKITTI folders and writes map.npz / map.ply; reading and
writing MCAP recordings and ROS 2 bags, drawing pictures and running on Ray each need an extra
(`pip install "tisem[mcap]"`, `[viz]`, `[ray]`, or `[all]`). A feature whose extra is missing
stops with one line that names it (`MissingExtra`), not with an import traceback.
"""

from __future__ import annotations

import importlib
from types import ModuleType

# top-level module -> the extra that installs it
EXTRA_OF_MODULE = {
    "mcap": "mcap",
    "mcap_ros2": "mcap",
    "mcap_protobuf": "mcap",
    "rosbags": "mcap",
    "foxglove_schemas_protobuf": "mcap",
    "google": "mcap",
    "zstandard": "mcap",
    "lz4": "mcap",
    "matplotlib": "viz",
    "ray": "ray",
}
WHAT_NEEDS = {
    "mcap": "MCAP recordings and ROS 2 bags",
    "viz": "pictures (matplotlib)",
    "ray": "fleet mapping and batch runs (Ray)",
}


class MissingExtra(ImportError):
    """A feature needs an optional dependency that is not installed; the message names the
    extra that installs it."""


def install_hint(extra: str) -> str:
    return f'pip install "tisem[{extra}]"'


def missing_extra(exc: ImportError) -> MissingExtra | None:
    """The `MissingExtra` that a failed import of an optional dependency means; None when the
    module that failed is not one of the extras' (a real bug: let it propagate)."""
    if isinstance(exc, MissingExtra):
        return exc
    name = (getattr(exc, "name", None) or "").split(".")[0]
    extra = EXTRA_OF_MODULE.get(name)
    if extra is None:
        return None
    return MissingExtra(
        f"{WHAT_NEEDS[extra]} need the '{extra}' extra (module {name!r} is not "
        f"installed): {install_hint(extra)}"
    )


def require(module: str) -> ModuleType:
    """Import `module`, an optional dependency; `MissingExtra` when it is not installed."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        missing = missing_extra(exc)
        if missing is None:
            raise
        raise missing from None
