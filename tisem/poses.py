"""What a sensor pose may be: the one rule every reader and the mapper check poses by."""

from __future__ import annotations

import numpy as np

# No position on or near the Earth is farther than this from any Earth-fixed origin (UTM,
# ECEF, a local map frame): a pose beyond it is corrupt data, not a place.
MAX_POSITION_M = 2.0e7
# How far R^T R may stray from the identity: poses stored with 9 significant digits (KITTI's
# poses.txt) are orthonormal to ~1e-8; 1e-3 still refuses any visible scaling or shear.
ROTATION_TOLERANCE = 1.0e-3


def pose_problem(T: np.ndarray) -> str | None:
    """Why the 4x4 rigid transform T cannot be a sensor pose, or None when it can.

    A pose is a rotation (orthonormal, determinant +1, within ROTATION_TOLERANCE) and a finite
    translation within MAX_POSITION_M; its last row is 0 0 0 1.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        return f"a pose is a 4x4 matrix, got shape {T.shape}"
    if not np.all(np.isfinite(T)):
        return "the pose has NaN/inf entries"
    if np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        return f"the pose's last row is {T[3].tolist()}, not [0, 0, 0, 1]"
    R = T[:3, :3]
    det = float(np.linalg.det(R))
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if off > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        scale = float(np.cbrt(abs(det))) if det else 0.0
        what = (
            "mirrored"
            if det < 0
            else "singular"
            if abs(det) < 1e-6
            else f"scaled by {scale:.4g}"
            if abs(scale - 1.0) > ROTATION_TOLERANCE
            else "not orthonormal"
        )
        return (
            f"the pose's rotation is not a rotation ({what}: det {det:.6g}, "
            f"|R^T R - I| = {off:.3g})"
        )
    dist = float(np.abs(T[:3, 3]).max())
    if dist > MAX_POSITION_M:
        return (
            f"the pose's position is {dist:.3g} m from the origin; no real pose is farther "
            f"than {MAX_POSITION_M:.0e} m"
        )
    return None
