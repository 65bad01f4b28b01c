"""The map's sizing rules (`tisem.geometry.MapGeometry`), in plain Python: no Taichi runtime."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tisem.kernels.layout import LEAF, MAX_REACH_BLK, TOP

from tisem.config import MapperConfig
from tisem.geometry import MapGeometry, block_aligned_origin

REPO = Path(__file__).resolve().parents[1]


def test_geometry_needs_no_taichi_runtime():
    """Sizing a map (even a refused one) starts no Taichi runtime: it runs in a process that
    never initialises Taichi."""
    code = (
        "from tisem.config import MapperConfig\n"
        "from tisem.geometry import MapGeometry\n"
        "import taichi.lang.impl as impl\n"
        "g = MapGeometry.from_config(MapperConfig())\n"
        "try:\n"
        "    MapGeometry.from_config(MapperConfig(window_xy_m=50.0))\n"
        "except ValueError:\n"
        "    pass\n"
        "assert impl.get_runtime().prog is None, 'a Taichi runtime was started'\n"
        "print(g.table_half_blk)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        cwd=REPO,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "(108, 108, 35)"


def test_default_geometry_by_hand():
    """The default config (st, 0.2 m voxels, 80 m range, 100 m x 24 m window, L <= 1.2 m)."""
    g = MapGeometry.from_config(MapperConfig())
    assert g.resolution_m == 0.2
    assert g.kernel_radius_vox == 7  # ceil(1.2 / 0.2 + 0.5)
    assert g.reach_blk == 2  # ceil(1.2 / 0.8)
    np.testing.assert_array_equal(g.window_half_vox, [500, 500, 120])
    # kept points: within 80 m (401 voxels) in x, y; in z the window less the kernel radius
    np.testing.assert_array_equal(g.point_limit_vox, [401, 401, 120 - 7 - 1])
    assert g.table_half_blk == (101 + 7, 101 + 7, 28 + 7)  # ceil(limit / 4) + 2 reach + 3
    assert g.table_cells == 217 * 217 * 71
    assert g.storage_extent == (2048, 2048, 512)  # powers of two >= 2 (half + 2 TOP) + 1
    assert g.scan_reach_vox == 401 + 7


def test_csm_has_no_kernel_reach():
    g = MapGeometry.from_config(MapperConfig(mode="csm"))
    assert g.kernel_radius_vox == 0 and g.reach_blk == 0
    np.testing.assert_array_equal(g.point_limit_vox, [401, 401, 119])
    assert g.table_half_blk == (104, 104, 33)


@pytest.mark.parametrize("seed", range(20))
def test_sizes_hold_every_scan_and_its_kernels(seed):
    """For random configs that work: a kept point's voxel plus its kernel radius lies inside
    the window; the table holds every block a kept point or a kernel from it can reach, with
    the margin the kernel update reads around a receiving voxel; storage does not alias."""
    rng = np.random.default_rng(seed)
    res = float(rng.choice([0.1, 0.2, 0.25, 0.4]))
    mode = str(rng.choice(["st", "bki", "csm"]))
    max_range = float(rng.uniform(10, 90))
    ell_max = float(rng.uniform(1.0, 2.0)) * res * 3
    cfg = MapperConfig(
        mode=mode,
        resolution_m=res,
        max_range_m=max_range,
        ell_min_m=res,
        ell_max_m=ell_max,
        ell_fixed_vox=float(rng.integers(1, 5)),
        window_xy_m=max_range + float(rng.uniform(3, 30)),
        window_z_m=float(rng.uniform(10, 30)),
    )
    try:
        g = MapGeometry.from_config(cfg)
    except ValueError as exc:  # (a refused config names its limit)
        assert "must hold the scan" in str(exc) or "leaf blocks" in str(exc)
        return
    half, limit, radius = g.window_half_vox, g.point_limit_vox, g.kernel_radius_vox
    assert np.all(limit + radius < half)
    assert np.all(limit[:2] >= math.ceil(max_range / res))  # any point in range is kept
    assert radius >= math.ceil(cfg.reach_m / res)
    assert g.reach_blk <= MAX_REACH_BLK and g.reach_blk * LEAF * res >= cfg.reach_m
    reach = np.array(g.table_half_blk) * LEAF
    assert np.all(reach >= limit + 2 * g.reach_blk * LEAF + 2 * LEAF)
    for n, h in zip(g.storage_extent, half):
        assert n & (n - 1) == 0 and n % TOP == 0 and n >= 2 * (h + 2 * TOP) + 1


def test_impossible_configs_are_refused_with_the_figure():
    with pytest.raises(ValueError, match=r"must hold the scan .*need >= 82.0 m / 22.0 m"):
        MapGeometry.from_config(MapperConfig(window_xy_m=60.0))
    with pytest.raises(ValueError, match=r"longer than 2 leaf blocks \(1.60 m at 0.2 m voxels\)"):
        MapGeometry.from_config(MapperConfig(ell_max_m=2.0, window_xy_m=110.0))
    with pytest.raises(ValueError, match=r"needs a scan table of [\d,]+ leaf blocks"):
        MapGeometry.from_config(
            MapperConfig(
                max_range_m=900.0,
                resolution_m=0.02,
                window_xy_m=910.0,
                ell_min_m=0.04,
                ell_max_m=0.16,
            )
        )


def test_block_aligned_origin():
    got = block_aligned_origin(np.array([0, 31, 32, -1, -32, -33, 1000]))
    np.testing.assert_array_equal(got, [0, 0, 32, -32, -32, -64, 992])
    assert got.dtype == np.int64 and np.all(got % TOP == 0)
