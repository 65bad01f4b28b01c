"""The files of a results folder: config.yaml and run.json first, metrics.json at the end,
then the map files (map.npz, map.ply, map_bev.png). Per-point predictions are written scan by
scan (`tisem.io.kitti_predictions.write_predictions`), checkpoints to checkpoint/; map_mcap.py adds
map.mcap, the ROS 2 bag map_ros2/ (`write_recording_maps`) and mcap_report.json,
map_kitti.py's embedded default its synthetic/ sequence, render.py compare.png.
`clear_previous_run` removes exactly these, for --overwrite."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tisem.config import MapperConfig, RunConfig, save_config, to_dict

if TYPE_CHECKING:
    from tisem.mapper import Mapper
    from tisem.scan import Scan
    from tisem.snapshot import MapSnapshot

log = logging.getLogger(__name__)

__all__ = [
    "write_run_info",
    "write_metrics",
    "write_map_files",
    "write_recording_maps",
    "is_results_folder",
    "clear_previous_run",
    "RUN_FILES",
    "MAP_BAG",
]

# what a run writes at the top of its folder
RUN_FILES = (
    "config.yaml",
    "run.json",
    "metrics.json",
    "map.npz",
    "map.ply",
    "map_bev.png",
    "map.mcap",
    "mcap_report.json",
    "compare.png",
    "map_dynamic.ply",
)
CHECKPOINT_FILES = ("checkpoint.npz", ".checkpoint.npz.*.tmp")
PREDICTION_FILES = ("*.label", "*.label.tmp", "*.dynamic", "*.dynamic.tmp")
MAP_BAG = "map_ros2"  # the map as a rosbag2 folder, for `ros2 bag play` + RViz
MAP_BAG_FILES = ("metadata.yaml", f"{MAP_BAG}_*.mcap")


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


def write_map_files(
    out_dir: Path,
    mapper: Mapper,
    config: MapperConfig,
    trajectory: np.ndarray,
    progress: bool = False,
) -> dict[str, Path]:
    """Write the finished map of `mapper` (built with `config`) into `out_dir`; `trajectory`
    (M, 3) is drawn on the top-down picture; `progress`: a bar over the files. Returns
    {kind: path}."""
    from tqdm import tqdm

    from tisem.extras import MissingExtra, require
    from tisem.io.export import write_ply
    from tisem.io.mapfile import save_map

    paths = {"npz": out_dir / "map.npz", "ply": out_dir / "map.ply", "bev": out_dir / "map_bev.png"}
    with tqdm(total=len(paths) + 1, unit="step", desc="map files", disable=not progress) as bar:
        bar.set_postfix_str("snapshot")
        snap = mapper.snapshot()
        bar.update()
        bar.set_postfix_str(paths["npz"].name)
        save_map(paths["npz"], snap, to_dict(config), dict(mapper.state()))
        bar.update()
        bar.set_postfix_str(paths["ply"].name)
        # free space: map.ply is the static map, map_dynamic.ply the voxels seen through
        # (trails of what moved, with the class they held); map.npz keeps both, and the
        # top view draws the removed voxels in the colour of label 0 (black)
        static, dynamic = snap.layers()
        if dynamic is not None:
            paths["dynamic_ply"] = out_dir / "map_dynamic.ply"
            write_ply(paths["dynamic_ply"], dynamic)
        write_ply(paths["ply"], static)
        bar.update()
        try:  # the picture is the one output that needs an extra
            require("matplotlib")
            from tisem.viz.bev import render_bev
        except MissingExtra as exc:
            log.warning("no %s: %s", paths["bev"].name, exc)
            del paths["bev"]
            return paths
        if len(snap):
            bar.set_postfix_str(paths["bev"].name)
            render_bev(
                snap,
                paths["bev"],
                trajectory_xy=trajectory[:, :2],
                title=f"tisem map ({config.mode}), {len(snap):,} voxels",
            )
        else:
            log.warning("the map is empty: no %s written", paths["bev"].name)
            del paths["bev"]
        bar.update()
    return paths


def write_recording_maps(
    out_dir: Path,
    snapshot: MapSnapshot,
    frame_id: str,
    scans: Iterable[tuple[Scan, np.ndarray]] | None = None,
) -> dict:
    """map.mcap (foxglove.PointCloud, for Foxglove) and map_ros2/ (a rosbag2 folder of
    sensor_msgs/PointCloud2, for `ros2 bag play` and RViz), both on /semantic_map, with the
    scans (Scan, mapped train ids) on /semantic_scans; the scans are read once, both files
    are written as they come. With free space, /semantic_map is the static map and the voxels
    seen through go to /semantic_map_dynamic, as map.ply and map_dynamic.ply split them; scans
    given as (Scan, mapped, dynamic flags) put their flagged points on /dynamic_points too.
    Returns {"mcap": path, "bag": path, "voxels", "dynamic_voxels", "scans"}."""
    from tisem.io.mcap_writer import DYNAMIC_MAP_TOPIC, write_map_mcap
    from tisem.io.rosbag_map import MapBag
    from tisem.io.stamps import map_stamp_ns

    scans = iter(scans) if scans is not None else iter(())
    first = next(scans, None)
    stamp_ns = map_stamp_ns(snapshot, first[0] if first is not None else None)
    paths = {"mcap": out_dir / "map.mcap", "bag": out_dir / MAP_BAG}
    static, dynamic = snapshot.layers()
    with MapBag(paths["bag"], frame_id) as bag:
        bag.write_map(static, stamp_ns)
        if dynamic is not None:
            bag.write_map(dynamic, stamp_ns, DYNAMIC_MAP_TOPIC)

        def both() -> Iterator[tuple]:  # (Scan, mapped) or (Scan, mapped, dynamic flags)
            for item in [first] if first is not None else []:
                bag.write_scan(*item)
                yield item
            for item in scans:
                bag.write_scan(*item)
                yield item

        info = write_map_mcap(
            paths["mcap"],
            static,
            frame_id=frame_id,
            scans=both(),
            stamp_ns=stamp_ns,
            dynamic=dynamic,
        )
    return {
        **paths,
        "voxels": info["voxels"],
        "dynamic_voxels": info["dynamic_voxels"],
        "scans": info["scans"],
    }


def is_results_folder(folder: Path) -> bool:
    """Whether `folder` holds a tisem run's results (its run.json)."""
    return (Path(folder) / "run.json").is_file()


def clear_previous_run(folder: Path) -> int:
    """Remove what a run wrote in `folder` (module docstring): the files of RUN_FILES,
    sequences/*/predictions/ label files, checkpoint/ files and the synthetic/ sequence;
    folders left empty go too, anything else stays. Returns the number of files removed."""
    from tisem.synth.sequence import clear_sequence

    folder = Path(folder)
    removed = 0

    def remove(paths) -> None:
        nonlocal removed
        for path in paths:
            if path.is_file() or path.is_symlink():
                path.unlink()
                removed += 1

    remove(folder / name for name in RUN_FILES)
    remove(p for pattern in MAP_BAG_FILES for p in (folder / MAP_BAG).glob(pattern))
    _remove_empty(folder / MAP_BAG, up_to=folder)
    for predictions in folder.glob("sequences/*/predictions"):
        remove(p for pattern in PREDICTION_FILES for p in predictions.glob(pattern))
        _remove_empty(predictions, up_to=folder)
    checkpoint = folder / "checkpoint"
    remove(p for pattern in CHECKPOINT_FILES for p in checkpoint.glob(pattern))
    _remove_empty(checkpoint, up_to=folder)
    synthetic = folder / "synthetic"
    if synthetic.is_dir():
        removed += clear_sequence(synthetic)
        _remove_empty(synthetic, up_to=folder)
    return removed


def _remove_empty(path: Path, up_to: Path) -> None:
    """Remove `path` and its parents below `up_to` while they are empty folders."""
    while path != up_to and path.is_dir() and not any(path.iterdir()):
        path.rmdir()
        path = path.parent
