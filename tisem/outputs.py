"""The files of a results folder: config.yaml and run.json first, metrics.json at the end,
then the map files (map.npz, map.ply, map_bev.png). Per-point predictions are written scan by
scan (`tisem.io.semantickitti.write_predictions`)."""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tisem.config import MapperConfig, RunConfig, save_config, to_dict

if TYPE_CHECKING:
    from tisem.mapper import Mapper

log = logging.getLogger(__name__)

__all__ = ["write_run_info", "write_metrics", "write_map_files"]


def write_run_info(out_dir: Path, cfg: RunConfig, info: dict) -> None:
    """config.yaml (the resolved config, so the run can be repeated) and run.json (what was
    read: data, options, sequence)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out_dir / "config.yaml")
    (out_dir / "run.json").write_text(json.dumps(info, indent=2, default=str))


def write_metrics(out_dir: Path, metrics: dict) -> Path:
    path = out_dir / "metrics.json"
    path.write_text(json.dumps(metrics, indent=2))
    return path


def write_map_files(out_dir: Path, mapper: Mapper, config: MapperConfig,
                    trajectory: np.ndarray) -> dict[str, Path]:
    """Write the finished map of `mapper` (built with `config`) into `out_dir`; `trajectory`
    (M, 3) is drawn on the top-down picture. Returns {kind: path}."""
    from tisem.io.export import write_ply
    from tisem.io.mapfile import save_map
    from tisem.viz.bev import render_bev

    snap = mapper.snapshot()
    paths = {"npz": out_dir / "map.npz", "ply": out_dir / "map.ply",
             "bev": out_dir / "map_bev.png"}
    save_map(paths["npz"], snap, to_dict(config), dict(mapper.state()))
    write_ply(paths["ply"], snap)
    if len(snap):
        render_bev(snap, paths["bev"], trajectory_xy=trajectory[:, :2],
                   title=f"tisem map ({config.mode}), {len(snap):,} voxels")
    else:
        log.warning("the map is empty: no %s written", paths["bev"].name)
        del paths["bev"]
    return paths
