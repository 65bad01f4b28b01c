"""Pictures: the top-down map PNG and the 3-panel region comparison."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from tisem.io.mapfile import save_map
from tisem.labels import CLASS_COLORS_RGB, LEARNING_MAP_INV
from tisem.snapshot import MapSnapshot
from tisem.viz import render_bev, render_comparison
from tisem.viz.bev import PNG_KEY, TopDownGrid, top_labels

ROAD, BUILDING, SIDEWALK, VEGETATION = 9, 13, 11, 15
WHITE = (255, 255, 255)


def road_and_building(res: float = 0.2) -> MapSnapshot:
    """A 10 m x 10 m road plane (z = 0) on [0, 10)^2 with a 2 m x 2 m x 2.8 m building on
    [2, 4) x [6, 8) standing on it, and one voxel without evidence floating above the road."""
    n = round(10 / res)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    road = np.stack([i.ravel(), j.ravel(), np.zeros(i.size, int)], 1)
    b = np.arange(round(2 / res))
    bi, bj, bk = np.meshgrid(
        b + round(2 / res), b + round(6 / res), np.arange(1, 15), indexing="ij"
    )
    building = np.stack([bi.ravel(), bj.ravel(), bk.ravel()], 1)
    empty = np.array([[round(7 / res), round(3 / res), 30]])
    keys = np.concatenate([road, building, empty]).astype(np.int64)
    counts = np.zeros((len(keys), 20), np.float32)
    counts[: len(road), ROAD] = 3.0
    counts[len(road) : len(road) + len(building), BUILDING] = 2.0
    order = MapSnapshot.sort_order(keys)
    return MapSnapshot(
        keys[order], counts[order], np.zeros(len(keys)), np.full(len(keys), 0.4, np.float32), res
    )


def png_pixel(img: np.ndarray, georef: dict, x: float, y: float) -> tuple:
    """The RGB of the PNG pixel showing world (x, y), using the georeference in the PNG."""
    p, zoom = georef["pixel_m"], georef["zoom"]
    col = georef["left_px"] + (x - georef["x0"]) / p * zoom
    row = georef["top_px"] + (georef["y0"] + georef["height"] * p - y) / p * zoom
    return tuple(int(c) for c in img[int(row), int(col), :3])


def test_top_labels_keeps_the_highest_item_per_cell():
    grid = TopDownGrid.covering(0, 0, 2, 1, 1.0)
    assert (grid.width, grid.height) == (2, 1)
    xy = np.array([[0.5, 0.5], [0.2, 0.7], [0.9, 0.1], [1.5, 0.5], [5.0, 0.5]])
    image = top_labels(
        grid, xy, z=np.array([1.0, 3.0, 2.0, 0.0, 9.0]), labels=np.array([1, 2, 3, 4, 5])
    )
    assert image.tolist() == [[2, 4]]  # the point outside the grid is ignored


def test_bev_png_size_and_class_colours(tmp_path):
    snap = road_and_building()
    out = tmp_path / "map_bev.png"
    cell = render_bev(
        snap, out, trajectory_xy=[(0.5, 5.0), (6.0, 5.0), (12.0, 5.0)], title="road + building"
    )
    assert cell == pytest.approx(0.2)
    with Image.open(out) as im:
        georef = json.loads(im.text[PNG_KEY])
        img = np.asarray(im.convert("RGB"))
    assert (img.shape[1], img.shape[0]) == (georef["image_w"], georef["image_h"])
    # the view is the map (x 0..10, y 0..10) widened to the trajectory's end (+ 2 cells)
    assert (georef["x0"], georef["y0"]) == (0.0, 0.0)
    assert georef["height"] == 50 and georef["width"] == 62
    assert georef["zoom"] >= 1 and img.shape[0] >= 50 * georef["zoom"]

    road, building = tuple(CLASS_COLORS_RGB[ROAD]), tuple(CLASS_COLORS_RGB[BUILDING])
    for x, y in [(8.1, 2.1), (5.3, 3.3), (9.9, 9.9), (7.1, 3.1)]:  # (7.1, 3.1): under the
        assert png_pixel(img, georef, x, y) == road, (x, y)  # evidence-less voxel
    for x, y in [(2.1, 6.1), (3.0, 7.0), (3.9, 7.9)]:  # highest voxel wins
        assert png_pixel(img, georef, x, y) == building, (x, y)
    for x, y in [(11.0, 2.0), (12.0, 9.0)]:  # beyond the map
        assert png_pixel(img, georef, x, y) == WHITE, (x, y)
    assert png_pixel(img, georef, 9.0, 5.0) not in (road, WHITE)  # the trajectory line


def test_bev_coarsens_to_max_pixels(tmp_path):
    snap = road_and_building()
    out = tmp_path / "small.png"
    # 10 m / 0.2 m = 50 cells > 20: the cell becomes 3 voxels wide -> 17 cells
    assert render_bev(snap, out, max_pixels=20) == pytest.approx(0.6)
    with Image.open(out) as im:
        georef = json.loads(im.text[PNG_KEY])
        img = np.asarray(im.convert("RGB"))
    assert (georef["width"], georef["height"]) == (17, 17)
    assert png_pixel(img, georef, 8.0, 2.0) == tuple(CLASS_COLORS_RGB[ROAD])
    # the cell [1.8, 2.4) holds road columns and building columns: the building is higher
    assert png_pixel(img, georef, 1.9, 6.5) == tuple(CLASS_COLORS_RGB[BUILDING])


def test_bev_of_an_empty_map_on_black(tmp_path):
    snap = MapSnapshot(
        np.zeros((0, 3), np.int64),
        np.zeros((0, 20), np.float32),
        np.zeros(0),
        np.zeros(0, np.float32),
        0.2,
    )
    out = tmp_path / "empty.png"
    assert render_bev(snap, out, background="black") == pytest.approx(0.2)
    with Image.open(out) as im:
        georef = json.loads(im.text[PNG_KEY])
        img = np.asarray(im.convert("RGB"))
    assert png_pixel(img, georef, 0.1, 0.1) == (0, 0, 0)


# --------------------------------------------------------------------------- comparison


def _write_labels(path: Path, train_ids: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    LEARNING_MAP_INV[train_ids].astype("<u4").tofile(path)


def _row(T: np.ndarray) -> str:
    return " ".join(f"{v:.9g}" for v in T[:3, :4].ravel())


@pytest.fixture
def results_dir(tmp_path) -> Path:
    """A 3-scan SemanticKITTI sequence and a results folder for it, written by hand.

    Each scan is a 40 x 40 grid of ground points (0.5 m apart) in front of the sensor: road
    where x < 0, sidewalk elsewhere. The network gets every 4th point wrong (vegetation), the
    map every 20th, so the region's accuracies are exactly 0.75 and 0.95. The sensor moves
    1 m along x per scan; poses are stored in the camera frame, as SemanticKITTI does.
    """
    seq = tmp_path / "seq"
    g = np.arange(-10, 10, 0.5)
    x, y = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, -1.7), np.zeros(x.size)], 1)
    Tr = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], float)
    (seq / "velodyne").mkdir(parents=True)
    (seq / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: " + _row(Tr) + "\n")
    poses = []
    k = np.arange(len(pts))
    for i in range(3):
        T_lidar = np.eye(4)
        T_lidar[0, 3] = float(i)
        poses.append(_row(Tr @ T_lidar @ np.linalg.inv(Tr)))
        pts.astype("<f4").tofile(seq / "velodyne" / f"{i:06d}.bin")
        gt = np.where(pts[:, 0] + i < 0, ROAD, SIDEWALK)
        _write_labels(seq / "labels" / f"{i:06d}.label", gt)
        _write_labels(seq / "predictions" / f"{i:06d}.label", np.where(k % 4 == 1, VEGETATION, gt))
        _write_labels(
            tmp_path / "results" / "sequences" / "08" / "predictions" / f"{i:06d}.label",
            np.where(k % 20 == 3, VEGETATION, gt),
        )
    (seq / "poses.txt").write_text("\n".join(poses) + "\n")

    res = tmp_path / "results"
    (res / "run.json").write_text(
        json.dumps(
            {"data": str(seq), "sequence": "08", "first": 0, "last": 2, "scan_ids": [0, 1, 2]}
        )
    )
    (res / "config.yaml").write_text(
        yaml.safe_dump(
            {"mapper": {"max_range_m": 80.0}, "input": "predictions", "first": 0, "last": 2}
        )
    )
    return res


def test_comparison_renders_with_region_accuracies(results_dir):
    result = render_comparison(results_dir)
    assert result["out"] == results_dir / "compare.png"
    assert result["region"] == (-19.0, -20.0, 21.0, 20.0)  # 40 m around the middle sensor
    assert result["scans"] == [0, 1, 2] and result["points"] == 3 * 1600
    assert result["accuracy"]["network"] == pytest.approx(0.75)
    assert result["accuracy"]["map"] == pytest.approx(0.95)
    # the network is wrong at every 4th point, the map at every 20th: they differ at both
    assert result["changed"] == 3 * (400 + 80)
    with Image.open(result["out"]) as im:
        assert im.width > 3 * 400 and im.height > 400


def test_comparison_without_ground_truth_draws_what_the_map_changed(results_dir):
    """No labels/: the third panel shows the points whose map label is not the network's."""
    shutil.rmtree(Path(json.loads((results_dir / "run.json").read_text())["data"]) / "labels")
    result = render_comparison(results_dir)
    assert result["accuracy"] == {"network": None, "map": None}
    assert result["changed"] == 3 * (400 + 80) and result["points"] == 3 * 1600
    with Image.open(result["out"]) as im:
        rgb = np.asarray(im.convert("RGB"))
    third = rgb[: int(0.85 * rgb.shape[0]), 2 * rgb.shape[1] // 3 :]  # (the legend is below)
    # the changed points are the network's wrong vegetation (now road or sidewalk) and the
    # map's own vegetation: the third panel holds sidewalk's colour and vegetation's
    for name in (SIDEWALK, VEGETATION):
        assert (third == CLASS_COLORS_RGB[name]).all(axis=2).any(), name


def _render_app():
    path = Path(__file__).resolve().parents[1] / "apps" / "render.py"
    spec = importlib.util.spec_from_file_location("tisem_render_app", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_render_app_region_scan_and_bev(results_dir, tmp_path, capsys):
    app = _render_app()
    out = tmp_path / "one.png"
    assert (
        app.main(
            [str(results_dir), "--scan", "2", "--region", "0", "-5", "10", "5", "--out", str(out)]
        )
        == 0
    )
    assert out.stat().st_size > 0
    assert "map      accuracy: 95.00 %" in capsys.readouterr().out

    save_map(
        results_dir / "map.npz",
        road_and_building(),
        {"mode": "st"},
        {"trajectory_xy": [[0.5, 5.0], [9.0, 5.0]]},
    )
    assert app.main([str(results_dir), "--bev"]) == 0
    assert (results_dir / "map_bev.png").stat().st_size > 0

    assert app.main([str(results_dir), "--scan", "99"]) == 2  # bad input
    assert "scan 99 is not a mapped scan" in capsys.readouterr().err
