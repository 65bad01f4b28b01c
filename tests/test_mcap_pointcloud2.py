"""PointCloud2 / foxglove.PointCloud <-> numpy against a numpy reference, through real CDR and
protobuf bytes: any field order, padding, point_step, endianness, count > 1, padded rows."""
from __future__ import annotations

import io
from types import SimpleNamespace

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from tisem.io import pointcloud2 as pc2
from tisem.io.mcap_writer import Ros2McapWriter


def ros_round_trip(arr: np.ndarray, frame_id: str = "velodyne"):
    """Encode as PointCloud2 CDR in an MCAP and decode with mcap-ros2-support."""
    buf = io.BytesIO()
    with Ros2McapWriter(buf, compression="none") as w:
        w.write_cloud("/c", arr, frame_id, 1_500_000_000, 1_500_000_000)
    buf.seek(0)
    (_, _, _, msg), = make_reader(buf, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
    return msg


def reference(n: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {"x": rng.normal(size=n), "y": rng.normal(size=n), "z": rng.normal(size=n),
            "intensity": rng.random(n), "label": rng.integers(0, 260, n),
            "prob": rng.random((n, 20))}


def pack(ref: dict, order: str, layout: list, itemsize: int) -> np.ndarray:
    """`layout`: (name, numpy type, offset[, shape]) in any order, with gaps = padding."""
    dtype = np.dtype({"names": [f[0] for f in layout],
                      "formats": [(order + f[1], f[3]) if len(f) > 3 else order + f[1]
                                  for f in layout],
                      "offsets": [f[2] for f in layout], "itemsize": itemsize})
    arr = np.zeros(len(ref["x"]), dtype)
    for f in layout:
        arr[f[0]] = ref[f[0]]
    return arr


SHUFFLED = [("label", "u2", 0), ("z", "f4", 4), ("intensity", "f8", 8), ("x", "f4", 20),
            ("y", "f4", 28)]                                       # gaps at 2-3, 16-19, 24-27
XYZ_FIRST = [("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("label", "u4", 12),
             ("prob", "f4", 16, (20,))]


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("layout,itemsize", [(SHUFFLED, 40), (XYZ_FIRST, 96 + 8)],
                         ids=["shuffled-padded", "xyz-first-count20"])
def test_decode_matches_the_reference(order, layout, itemsize):
    ref = reference(257, seed=itemsize)
    msg = ros_round_trip(pack(ref, order, layout, itemsize))
    assert msg.is_bigendian == (order == ">") and msg.point_step == itemsize
    arr = pc2.ros_cloud_to_array(msg)
    xyz = pc2.xyz(arr)
    expect = np.stack([ref["x"], ref["y"], ref["z"]], 1).astype(np.float32)
    assert xyz.dtype == np.float32 and xyz.flags.c_contiguous
    assert np.array_equal(xyz, expect)
    labels = pc2.integer_labels(pc2.column(arr, "label"), "label")
    assert np.array_equal(labels, ref["label"])
    if pc2.has_field(arr, "prob"):
        prob = pc2.column(arr, "prob")
        assert prob.shape == (257, 20) and prob.dtype.isnative
        assert np.array_equal(prob, ref["prob"].astype(np.float32))


def test_organised_cloud_with_padded_rows():
    h, w, step, pad = 4, 5, 16, 8
    ref = reference(h * w, seed=3)
    arr = pack(ref, "<", [("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("label", "u2", 12)],
               step)
    rows = b"".join(arr[r * w:(r + 1) * w].tobytes() + b"\xee" * pad for r in range(h))
    msg = SimpleNamespace(fields=[SimpleNamespace(name=n, offset=o, datatype=d, count=1)
                                  for n, o, d in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7),
                                                  ("label", 12, 4))],
                          point_step=step, row_step=w * step + pad, height=h, width=w,
                          is_bigendian=False, data=rows)
    out = pc2.ros_cloud_to_array(msg)
    assert np.array_equal(pc2.xyz(out)[:, 0], ref["x"].astype(np.float32))
    assert np.array_equal(pc2.column(out, "label"), ref["label"].astype(np.uint16))


def test_field_quirks_count0_duplicates_empty_names():
    fields = [("x", 0, 7, 0), ("y", 4, 7, 1), ("z", 8, 7, 1), ("", 12, 2, 4), ("x", 12, 7, 1)]
    dtype = pc2.fields_dtype(fields, 16)
    assert dtype.names == ("x", "y", "z") and dtype.itemsize == 16


@pytest.mark.parametrize("fields,step,message", [
    ([("x", 0, 7, 1), ("label", 14, 6, 1)], 16, "does not fit"),
    ([("x", 0, 9, 1)], 16, "unknown datatype"),
    ([("", 0, 7, 1)], 16, "no fields"),
])
def test_inconsistent_layouts_are_clear_errors(fields, step, message):
    with pytest.raises(pc2.CloudFormatError, match=message):
        pc2.fields_dtype(fields, step)


def test_short_data_and_missing_fields_are_clear_errors():
    arr = pack(reference(10, 0), "<", XYZ_FIRST[:4], 16)
    msg = ros_round_trip(arr)
    msg.data = msg.data[:-1]
    with pytest.raises(pc2.CloudFormatError, match="need 160"):
        pc2.ros_cloud_to_array(msg)
    with pytest.raises(pc2.CloudFormatError, match=r"no field 'class'.*x:float32.*label:uint32"):
        pc2.column(arr, "class")


def test_label_types():
    assert pc2.integer_labels(np.array([1.0, 40.0], np.float32), "l").tolist() == [1, 40]
    with pytest.raises(pc2.CloudFormatError, match="whole"):
        pc2.integer_labels(np.array([1.5], np.float32), "l")
    with pytest.raises(pc2.CloudFormatError, match="probability field"):
        pc2.integer_labels(np.zeros((3, 2), np.uint8), "l")
    assert pc2.integer_labels(np.array([-1, 3], np.int8), "l").tolist() == [-1, 3]


def test_xyz_in_float64_takes_the_general_path():
    ref = reference(5, 1)
    arr = pack(ref, ">", [("z", "f8", 0), ("y", "f8", 8), ("x", "f8", 16)], 24)
    assert np.array_equal(pc2.xyz(arr)[:, 2], ref["z"].astype(np.float32))


def test_foxglove_round_trip_with_signed_unsigned_enums():
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    ref = reference(33, 2)
    arr = pack(ref, "<", [("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("label", "u2", 12),
                          ("intensity", "f8", 16)], 24)
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    msg = PointCloud.FromString(pc2.array_to_foxglove_cloud(arr, "map", 5, T).SerializeToString())
    assert [f.type for f in msg.fields] == [7, 7, 7, 3, 8]        # foxglove UINT16 = 3
    out = pc2.foxglove_cloud_to_array(msg)
    assert np.array_equal(out, arr) and msg.pose.position.z == 3
    with pytest.raises(pc2.CloudFormatError, match="little-endian"):
        pc2.array_to_foxglove_cloud(arr.astype(arr.dtype.newbyteorder(">")), "map", 0)
