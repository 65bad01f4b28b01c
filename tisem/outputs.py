"""Map files written at the end of a run: map.npz, map.ply, map_bev.png."""
from __future__ import annotations

import logging

from tisem.config import to_dict

log = logging.getLogger(__name__)


def write_map_files(result, cfg) -> dict:
    """Write the map of a finished run into its folder; returns {kind: path}."""
    from tisem.io.export import write_ply
    from tisem.io.mapfile import save_map
    from tisem.viz.bev import render_bev

    out = result.out_dir
    snap = result.mapper.snapshot()
    paths = {"npz": out / "map.npz", "ply": out / "map.ply", "bev": out / "map_bev.png"}
    save_map(paths["npz"], snap, to_dict(cfg.mapper), dict(result.mapper.state()))
    write_ply(paths["ply"], snap)
    if len(snap):
        render_bev(snap, paths["bev"], trajectory_xy=result.trajectory[:, :2],
                   title=f"tisem map ({cfg.mapper.mode}), {len(snap):,} voxels")
    else:
        log.warning("the map is empty: no %s written", paths["bev"].name)
        del paths["bev"]
    return paths
