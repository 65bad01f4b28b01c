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
    ((_, _, _, msg),) = make_reader(
        buf, decoder_factories=[DecoderFactory()]
    ).iter_decoded_messages()
    return msg


def reference(n: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "x": rng.normal(size=n),
        "y": rng.normal(size=n),
        "z": rng.normal(size=n),
        "intensity": rng.random(n),
        "label": rng.integers(0, 260, n),
        "prob": rng.random((n, 20)),
    }


def pack(ref: dict, order: str, layout: list, itemsize: int) -> np.ndarray:
    """`layout`: (name, numpy type, offset[, shape]) in any order, with gaps = padding."""
    dtype = np.dtype(
        {
            "names": [f[0] for f in layout],
            "formats": [(order + f[1], f[3]) if len(f) > 3 else order + f[1] for f in layout],
            "offsets": [f[2] for f in layout],
            "itemsize": itemsize,
        }
    )
    arr = np.zeros(len(ref["x"]), dtype)
    for f in layout:
        arr[f[0]] = ref[f[0]]
    return arr


SHUFFLED = [
    ("label", "u2", 0),
    ("z", "f4", 4),
    ("intensity", "f8", 8),
    ("x", "f4", 20),
    ("y", "f4", 28),
]  # gaps at 2-3, 16-19, 24-27
XYZ_FIRST = [
    ("x", "f4", 0),
    ("y", "f4", 4),
    ("z", "f4", 8),
    ("label", "u4", 12),
    ("prob", "f4", 16, (20,)),
]


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize(
    "layout,itemsize",
    [(SHUFFLED, 40), (XYZ_FIRST, 96 + 8)],
    ids=["shuffled-padded", "xyz-first-count20"],
)
def test_decode_matches_the_reference(order, layout, itemsize):
    ref = reference(257, seed=itemsize)
    msg = ros_round_trip(pack(ref, order, layout, itemsize))
    assert msg.is_bigendian == (order == ">") and msg.point_step == itemsize
    arr = pc2.ros_cloud_to_array(msg)
    xyz = pc2.xyz(arr)
    expect = np.stack([ref["x"], ref["y"], ref["z"]], 1).astype(np.float32)
    assert xyz.dtype == np.float32 and xyz.flags.c_contiguous
    assert np.array_equal(xyz, expect)
    labels, invalid = pc2.integer_labels(pc2.column(arr, "label"), "label")
    assert np.array_equal(labels, ref["label"]) and not invalid.any()
    if pc2.has_field(arr, "prob"):
        prob = pc2.column(arr, "prob")
        assert prob.shape == (257, 20) and prob.dtype.isnative
        assert np.array_equal(prob, ref["prob"].astype(np.float32))


def test_organised_cloud_with_padded_rows():
    h, w, step, pad = 4, 5, 16, 8
    ref = reference(h * w, seed=3)
    arr = pack(
        ref, "<", [("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("label", "u2", 12)], step
    )
    rows = b"".join(arr[r * w : (r + 1) * w].tobytes() + b"\xee" * pad for r in range(h))
    msg = SimpleNamespace(
        fields=[
            SimpleNamespace(name=n, offset=o, datatype=d, count=1)
            for n, o, d in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("label", 12, 4))
        ],
        point_step=step,
        row_step=w * step + pad,
        height=h,
        width=w,
        is_bigendian=False,
        data=rows,
    )
    out = pc2.ros_cloud_to_array(msg)
    assert np.array_equal(pc2.xyz(out)[:, 0], ref["x"].astype(np.float32))
    assert np.array_equal(pc2.column(out, "label"), ref["label"].astype(np.uint16))


def test_field_quirks_count0_duplicates_empty_names():
    fields = [("x", 0, 7, 0), ("y", 4, 7, 1), ("z", 8, 7, 1), ("", 12, 2, 4), ("x", 12, 7, 1)]
    dtype = pc2.fields_dtype(fields, 16)
    assert dtype.names == ("x", "y", "z") and dtype.itemsize == 16


@pytest.mark.parametrize(
    "fields,step,message",
    [
        ([("x", 0, 7, 1), ("label", 14, 6, 1)], 16, "does not fit"),
        ([("x", 0, 9, 1)], 16, "unknown datatype"),
        ([("", 0, 7, 1)], 16, "no fields"),
    ],
)
def test_inconsistent_layouts_are_clear_errors(fields, step, message):
    with pytest.raises(pc2.CloudFormatError, match=message):
        pc2.fields_dtype(fields, step)


def test_short_data_and_missing_fields_are_clear_errors():
    arr = pack(reference(10, 0), "<", XYZ_FIRST[:4], 16)
    msg = ros_round_trip(arr)
    msg.data = msg.data[:-1]
    with pytest.raises(pc2.CloudFormatError, match="data has 159 bytes.*needs 160"):
        pc2.ros_cloud_to_array(msg)
    with pytest.raises(pc2.CloudFormatError, match=r"no field 'class'.*x:float32.*label:uint32"):
        pc2.column(arr, "class")


def test_label_types():
    values, invalid = pc2.integer_labels(np.array([1.0, 40.0], np.float32), "l")
    assert values.tolist() == [1, 40] and not invalid.any()
    with pytest.raises(pc2.CloudFormatError, match="probability field"):
        pc2.integer_labels(np.zeros((3, 2), np.uint8), "l")
    values, invalid = pc2.integer_labels(np.array([-1, 3], np.int8), "l")
    assert values.tolist() == [-1, 3] and not invalid.any()


def test_float_labels_that_are_no_label_are_marked_invalid():
    """NaN, inf, huge, negative and fractional floats cannot be labels: 0 and marked, so the
    reader counts them as unknown (cast as they are, a 1e300 would wrap into a small class)."""
    raw = np.array(
        [40.0, np.nan, np.inf, -np.inf, 1e300, -1.0, 0.5, 2.0**32, 2.0**32 - 1, 10.0], np.float64
    )
    values, invalid = pc2.integer_labels(raw, "l")
    assert invalid.tolist() == [False, True, True, True, True, True, True, True, False, False]
    assert values.tolist() == [40, 0, 0, 0, 0, 0, 0, 0, 2**32 - 1, 10]


def _cloud(n=4, **overrides):
    arr = pack(reference(n, 0), "<", XYZ_FIRST[:4], 16)
    msg = SimpleNamespace(
        fields=[
            SimpleNamespace(name=nm, offset=o, datatype=d, count=1)
            for nm, o, d in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("label", 12, 6))
        ],
        point_step=16,
        row_step=16 * n,
        height=1,
        width=n,
        is_bigendian=False,
        data=arr.tobytes(),
    )
    for key, value in overrides.items():
        setattr(msg, key, value)
    return msg


@pytest.mark.parametrize(
    "overrides,message",
    [
        (dict(height=0), "declares no points, but the cloud carries 64 bytes"),
        (dict(width=0), "declares no points, but the cloud carries 64 bytes"),
        (dict(width=3, row_step=48), "data has 64 bytes; height 1 x row_step 48"),  # fewer points
        (dict(width=5, row_step=80), "data has 64 bytes; height 1 x row_step 80"),  # more points
        (dict(height=2, width=2, row_step=16), "row_step 16 < width 2 x point_step 16"),
        (dict(height=3, width=2, row_step=32), "data has 64 bytes; height 3 x row_step 32"),
        (dict(point_step=0), "point_step 0 is not in 1..65536"),
        (dict(point_step=2**32 - 1), "point_step 4294967295 is not in"),
        (dict(point_step=17, row_step=68), "data has 64 bytes"),
    ],
)
def test_layouts_that_do_not_match_the_data_are_refused(overrides, message):
    """Points must neither go missing nor be invented: the header must describe the data."""
    with pytest.raises(pc2.CloudFormatError, match=message):
        pc2.ros_cloud_to_array(_cloud(**overrides))


def test_an_empty_cloud_is_an_empty_array_and_a_padded_last_row_is_optional():
    assert len(pc2.ros_cloud_to_array(_cloud(width=0, row_step=0, data=b""))) == 0
    msg = _cloud(height=2, width=2, row_step=40)  # 8 bytes of padding a row
    rows = msg.data[:32] + b"\0" * 8 + msg.data[32:]
    for data in (rows, rows + b"\0" * 8):  # last row padded or not
        out = pc2.ros_cloud_to_array(_cloud(height=2, width=2, row_step=40, data=data))
        assert np.array_equal(out["x"], np.frombuffer(msg.data, "<f4")[::4])


@pytest.mark.parametrize(
    "fields,message",
    [
        (
            [("x", 0, 7, 1), ("y", 2, 7, 1), ("z", 8, 7, 1), ("label", 12, 6, 1)],
            r"fields 'x' \(bytes 0-4\) and 'y' \(bytes 2-6\) overlap",
        ),
        (
            [("x", 0, 7, 3), ("y", 12, 7, 1), ("z", 16, 7, 1), ("label", 20, 6, 1)],
            "field 'x' has 3 values per point",
        ),
        (
            [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("label", 10, 4, 1)],
            "fields 'label' .* and 'z' .* overlap",
        ),
    ],
)
def test_used_fields_must_be_single_and_apart(fields, message):
    arr = np.zeros(3, pc2.fields_dtype(fields, 24))
    with pytest.raises(pc2.CloudFormatError, match=message):
        pc2.check_used_fields(arr, ["x", "y", "z", "label"])
    if "overlap" in message:
        pc2.check_used_fields(arr, ["x", "label"] if "'y'" in message else ["x"])  # apart: fine


def test_foxglove_stride_zero_is_a_clear_error():
    with pytest.raises(pc2.CloudFormatError, match="point_stride 0"):
        pc2.foxglove_cloud_to_array(SimpleNamespace(point_stride=0, fields=[], data=b"x"))


def test_xyz_in_float64_takes_the_general_path():
    ref = reference(5, 1)
    arr = pack(ref, ">", [("z", "f8", 0), ("y", "f8", 8), ("x", "f8", 16)], 24)
    assert np.array_equal(pc2.xyz(arr)[:, 2], ref["z"].astype(np.float32))


def test_foxglove_round_trip_with_signed_unsigned_enums():
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    ref = reference(33, 2)
    arr = pack(
        ref,
        "<",
        [
            ("x", "f4", 0),
            ("y", "f4", 4),
            ("z", "f4", 8),
            ("label", "u2", 12),
            ("intensity", "f8", 16),
        ],
        24,
    )
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    msg = PointCloud.FromString(pc2.array_to_foxglove_cloud(arr, "map", 5, T).SerializeToString())
    assert [f.type for f in msg.fields] == [7, 7, 7, 3, 8]  # foxglove UINT16 = 3
    out = pc2.foxglove_cloud_to_array(msg)
    assert np.array_equal(out, arr) and msg.pose.position.z == 3
    with pytest.raises(pc2.CloudFormatError, match="little-endian"):
        pc2.array_to_foxglove_cloud(arr.astype(arr.dtype.newbyteorder(">")), "map", 0)
