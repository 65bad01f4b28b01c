"""What a map's kernels are built for and what they read, from its config and geometry: the
compile-time `KernelSettings` (kernels/params.py) and the map's one `ScanParams` value, whose
per-scan members (pose, time, stamp) are refreshed before every scan."""

from __future__ import annotations

import numpy as np
from taichi.lang.argpack import ArgPack

from tisem.config import MapperConfig
from tisem.free_space import decay_rule
from tisem.geometry import MapGeometry
from tisem.kernels.params import (
    ADAPTIVE_LENGTH,
    FIXED_LENGTH,
    NO_KERNEL,
    KernelSettings,
    new_scan_params,
)


def kernel_settings(cfg: MapperConfig, per_voxel: bool) -> KernelSettings:
    """The compile-time settings of a map's kernels for its config."""
    length = ADAPTIVE_LENGTH if cfg.adaptive else FIXED_LENGTH if cfg.uses_kernel else NO_KERNEL
    return KernelSettings(
        kernel_length=length,
        decay=decay_rule(cfg),
        unit_weight=cfg.point_weight == "unit",
        per_voxel=per_voxel,
        evidence_caps=bool(np.isfinite(cfg.evidence_caps_m).any()),
        long_kernel_classes=cfg.long_kernel_ids,
        # (no classes, no test: the share and the width are then no compile-time choice)
        long_kernel_share=float(cfg.long_kernel_share) if cfg.long_kernel_ids else 1.0,
        long_kernel_min_neighbours=cfg.long_kernel_min_neighbours if cfg.long_kernel_ids else 0,
    )


def scan_params(cfg: MapperConfig, geo: MapGeometry) -> ArgPack:
    """The map's ScanParams, with the constants of its config and geometry (`set_scan` fills
    in each scan's pose, time and stamp)."""
    res = geo.resolution_m
    tau = cfg.decay_tau_s
    return new_scan_params(
        rotation=np.eye(3, dtype=np.float32),
        translation_m=np.zeros(3),
        center_vox=np.zeros(3, np.int64),
        limit_vox=geo.point_limit_vox,
        min_range2_m2=cfg.min_range_m**2,
        max_range2_m2=cfg.max_range_m**2,
        min_z_m=cfg.min_z_m,
        max_z_m=cfg.max_z_m,
        resolution_m=res,
        inv_resolution=1.0 / res,
        time_rel_s=0.0,
        stamp=0,
        min_points=cfg.min_points,
        reach_blk=geo.reach_blk,
        fixed_length_m=cfg.ell_fixed_vox * res,
        length_min_m=cfg.ell_min_m,
        length_max_m=cfg.ell_max_m,
        prior=cfg.prior,
        sigma0=cfg.sigma0,
        kernel_cutoff=cfg.kernel_cutoff,
        inv_tau=0.0 if tau in (0.0, float("inf")) else 1.0 / tau,
    )


def set_scan(
    p: ArgPack,
    rotation: np.ndarray,
    translation_m: np.ndarray,
    center_vox: np.ndarray,
    time_rel_s: float,
    stamp: int,
) -> None:
    """A scan's members of the map's ScanParams: R_local_sensor, the sensor's local position
    and voxel, its map time and its number from 1 on."""
    p.rotation = rotation.astype(np.float32)
    p.translation_m = translation_m
    p.center_vox = center_vox
    p.time_rel_s = time_rel_s
    p.stamp = stamp
