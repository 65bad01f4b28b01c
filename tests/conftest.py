"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest
import taichi as ti
from helpers import fresh_runtime

# The real data lives beside the repository (licence: never copied into it).
KITTI_MINI = (
    Path(__file__).resolve().parents[1].parent / "shared" / "data" / "semantickitti_08_mini"
)


@pytest.fixture(scope="session")
def kitti_mini() -> Path:
    """Path to the SemanticKITTI 08 mini sequence (frames 0-4), or skip when it is absent."""
    if not (KITTI_MINI / "velodyne").is_dir():
        pytest.skip(
            f"real data not found at {KITTI_MINI} (SemanticKITTI 08 mini; kept out of "
            f"the repository for licence reasons)"
        )
    return KITTI_MINI


@pytest.fixture
def taichi_cpu():
    """A fresh Taichi runtime on the CPU with 2 threads (one Mapper per runtime)."""
    fresh_runtime()
    yield
    ti.reset()


@pytest.fixture
def taichi_debug():
    """A runtime with `debug=True`: out-of-bounds accesses raise instead of corrupting."""
    fresh_runtime(debug=True)
    yield
    ti.reset()
