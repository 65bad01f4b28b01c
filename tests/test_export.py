"""PLY export and the npz map / checkpoint files."""

from __future__ import annotations

import os
import zipfile

import numpy as np
import pytest
from plyfile import PlyData

from tisem.config import MapperConfig, to_dict
from tisem.io import mapfile
from tisem.io.export import read_ply, write_ply
from tisem.io.mapfile import (
    CHECKPOINT_NAME,
    MapFileError,
    load_checkpoint_file,
    load_map_file,
    save_checkpoint_file,
    save_map,
)
from tisem.labels import CLASS_COLORS_RGB, CLASS_NAMES, LEARNING_MAP_INV
from tisem.snapshot import MapSnapshot


def random_snapshot(seed: int = 0, m: int = 300, res: float = 0.2) -> MapSnapshot:
    """Sorted unique keys around a far-away origin (float32 centres must still be exact enough),
    sparse counters with some voxels carrying no evidence at all."""
    rng = np.random.default_rng(seed)
    keys = np.unique(rng.integers(-40, 40, size=(m, 3)) + np.array([5000, -3000, 10]), axis=0)
    keys = keys[MapSnapshot.sort_order(keys)].astype(np.int64)
    counts = np.zeros((len(keys), 20), np.float32)
    rows = np.arange(len(keys))
    counts[rows, rng.integers(1, 20, len(keys))] = rng.uniform(0.5, 5, len(keys))
    counts[rows, rng.integers(1, 20, len(keys))] += rng.uniform(0, 2, len(keys))
    counts[::17] = 0  # no evidence: label 0, probability 0
    return MapSnapshot(
        keys=keys,
        counts=counts,
        t_last=rng.uniform(0, 100, len(keys)),
        ell_m=rng.uniform(0.4, 0.8, len(keys)).astype(np.float32),
        resolution_m=res,
    )


def assert_same_snapshot(a: MapSnapshot, b: MapSnapshot) -> None:
    assert a.resolution_m == b.resolution_m
    for name in ("keys", "counts", "t_last", "ell_m"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)


# --------------------------------------------------------------------------- PLY


@pytest.mark.parametrize("binary", [True, False])
def test_ply_holds_the_voxels_labels_and_probabilities(tmp_path, binary):
    snap = random_snapshot()
    path = tmp_path / "map.ply"
    write_ply(path, snap, binary=binary)

    ply = PlyData.read(str(path))  # plain plyfile, as a viewer would
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"].data
    assert set(v.dtype.names) == {
        "x",
        "y",
        "z",
        "red",
        "green",
        "blue",
        "label",
        "raw_label",
        "probability",
    }
    assert v["x"].dtype == np.float32 and v["red"].dtype == np.uint8
    assert v["raw_label"].dtype == np.uint32 and v["probability"].dtype == np.float32
    assert len(v) == len(snap)
    centers = snap.centers().astype(np.float32)
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), centers)
    labels = snap.labels()
    np.testing.assert_array_equal(v["label"], labels)
    np.testing.assert_array_equal(v["raw_label"], LEARNING_MAP_INV[labels])
    np.testing.assert_allclose(v["probability"], snap.confidence(), rtol=1e-6)
    np.testing.assert_array_equal(
        np.stack([v["red"], v["green"], v["blue"]], 1), CLASS_COLORS_RGB[labels]
    )
    assert (v["label"][::17] == 0).all() and (v["probability"][::17] == 0).all()

    header = "\n".join(ply.comments)
    assert "resolution_m 0.2" in header
    assert all(name in header for name in CLASS_NAMES)

    back = read_ply(path)
    np.testing.assert_array_equal(back["xyz"], centers)
    np.testing.assert_array_equal(back["label"], labels)
    assert back["comments"] == list(ply.comments)


def test_ply_of_an_empty_map(tmp_path):
    snap = MapSnapshot(
        np.zeros((0, 3), np.int64),
        np.zeros((0, 20), np.float32),
        np.zeros(0),
        np.zeros(0, np.float32),
        0.1,
    )
    write_ply(tmp_path / "empty.ply", snap)
    assert len(read_ply(tmp_path / "empty.ply")["x"]) == 0


# --------------------------------------------------------------------------- map file


def test_map_file_round_trip_is_exact(tmp_path):
    snap = random_snapshot(1)
    config = to_dict(MapperConfig(mode="bki", tau_s=3.5))
    meta = {
        "scan_index": np.int64(41),
        "t_last_scan_s": 4.1,
        "origin": np.array([1.0, 2.0, 3.0]),
        "sequence": "08",
    }
    path = save_map(tmp_path / "map.npz", snap, config, meta)
    assert path == tmp_path / "map.npz"
    back, config_back, meta_back = load_map_file(path)
    assert_same_snapshot(snap, back)
    assert config_back == config
    assert meta_back == {
        "scan_index": 41,
        "t_last_scan_s": 4.1,
        "origin": [1.0, 2.0, 3.0],
        "sequence": "08",
    }
    with np.load(path) as npz:  # the class table travels with the map
        assert tuple(npz["class_names"]) == CLASS_NAMES
        np.testing.assert_array_equal(npz["class_colors_rgb"], CLASS_COLORS_RGB)
    # a MapperConfig object is accepted as well as a dict; nothing else is left in the folder
    save_map(tmp_path / "map.npz", snap, MapperConfig(mode="bki", tau_s=3.5))
    assert load_map_file(tmp_path / "map.npz")[1] == config
    assert sorted(os.listdir(tmp_path)) == ["map.npz"]


def test_checkpoint_round_trip(tmp_path):
    snap = random_snapshot(2)
    path = save_checkpoint_file(tmp_path / "ckpt", snap, {"mode": "st"}, {"scan_index": 7})
    assert path.name == CHECKPOINT_NAME
    back, config, meta = load_checkpoint_file(tmp_path / "ckpt")
    assert_same_snapshot(snap, back)
    assert config == {"mode": "st"} and meta == {"scan_index": 7}
    with pytest.raises(FileNotFoundError, match=CHECKPOINT_NAME):
        load_checkpoint_file(tmp_path / "nowhere")


def test_interrupted_checkpoint_keeps_the_previous_one(tmp_path, monkeypatch):
    old = random_snapshot(3)
    save_checkpoint_file(tmp_path, old, {"mode": "st"}, {"scan_index": 10})
    before = (tmp_path / CHECKPOINT_NAME).read_bytes()
    new = random_snapshot(4, m=2000)

    # 1. killed after the data is written but before the rename
    def no_replace(src, dst):
        raise KeyboardInterrupt("killed before rename")

    monkeypatch.setattr(mapfile.os, "replace", no_replace)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint_file(tmp_path, new, {"mode": "st"}, {"scan_index": 20})
    monkeypatch.undo()

    # 2. the writer dies half way through the file (disk full, crash)
    real_savez = np.savez

    def half_savez(f, **arrays):
        real_savez(f, **arrays)
        f.truncate(f.tell() // 2)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(mapfile.np, "savez", half_savez)
    with pytest.raises(OSError, match="No space"):
        save_checkpoint_file(tmp_path, new, {"mode": "st"}, {"scan_index": 20})
    monkeypatch.undo()

    assert (tmp_path / CHECKPOINT_NAME).read_bytes() == before
    assert os.listdir(tmp_path) == [CHECKPOINT_NAME]  # no temp files left behind
    back, _, meta = load_checkpoint_file(tmp_path)
    assert_same_snapshot(old, back)
    assert meta == {"scan_index": 10}


def _damage_truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _damage_flip(path):
    # corrupt the middle of the (compressed) counts member: zlib or CRC must notice
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("counts.npy")
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 200
    for i in range(start, start + 64):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def _other_npz(path):
    np.savez(path, points=np.zeros((3, 3)))


def _text(path):
    path.write_text("keys,counts\n1,2\n")


@pytest.mark.parametrize(
    "damage,message",
    [
        (_damage_truncate, "truncated or damaged"),
        (_damage_flip, "truncated or damaged"),
        (_other_npz, "not a tisem map file"),
        (_text, "not an npz archive"),
    ],
)
def test_damaged_or_foreign_file_gives_a_clear_error(tmp_path, damage, message):
    path = tmp_path / "map.npz"
    save_map(path, random_snapshot(5, m=3000), {"mode": "st"})
    damage(path)
    with pytest.raises(MapFileError, match=message) as info:
        load_map_file(path)
    assert str(path) in str(info.value)


def test_missing_map_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="map file not found"):
        load_map_file(tmp_path / "map.npz")
