"""Map geometry: the pure-Python sizing rules of a map (no Taichi)."""
from __future__ import annotations

import numpy as np

from kernels.layout import TOP


def block_aligned_origin(voxel: np.ndarray) -> np.ndarray:
    """The map origin (int64 global voxel index) for a map centred near `voxel`: aligned to
    a top cell of the SNode tree, so that local indices stay small and the tree's cells line
    up with the global grid."""
    return (np.asarray(voxel, np.int64) // TOP) * TOP
