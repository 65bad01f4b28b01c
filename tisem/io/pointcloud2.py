"""Point clouds in messages <-> numpy structured arrays.

Two carriers: ROS `sensor_msgs/PointCloud2` and `foxglove.PointCloud`. Both describe a point
as named fields at byte offsets inside a fixed stride, so one numpy dtype (names, offsets,
itemsize = stride) views the message bytes without copying — whatever the field order,
padding, point_step or endianness. Only the columns a caller asks for get copied (and
byte-swapped to native order).

Facts this relies on, all seen in real recordings: the two datatype enums differ (signed and
unsigned are swapped); `count` may be 0 (means 1); names may repeat or be empty (padding);
organised clouds may pad rows (`row_step > width * point_step`).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np

from tisem.io.stamps import ros_time, split_ns

if TYPE_CHECKING:
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

# sensor_msgs/PointField: INT8=1 UINT8=2 INT16=3 UINT16=4 INT32=5 UINT32=6 FLOAT32=7 FLOAT64=8
ROS_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
# foxglove PackedElementField: UINT8=1 INT8=2 UINT16=3 INT16=4 UINT32=5 INT32=6 FLOAT32=7 FLOAT64=8
FOXGLOVE_DATATYPES = {1: "u1", 2: "i1", 3: "u2", 4: "i2", 5: "u4", 6: "i4", 7: "f4", 8: "f8"}


MAX_POINT_STEP = 1 << 16  # bytes per point: far more than any sensor's fields need


class CloudFormatError(ValueError):
    """A cloud's layout is inconsistent (the message says what); the cloud cannot be used."""


def fields_dtype(
    fields: Iterable[tuple[str, int, int, int]],
    point_step: int,
    *,
    big_endian: bool = False,
    datatypes: dict = ROS_DATATYPES,
) -> np.dtype:
    """A structured dtype for one point. `fields`: (name, offset, datatype, count) tuples."""
    order = ">" if big_endian else "<"
    names, formats, offsets = [], [], []
    for name, offset, datatype, count in fields:
        if not name or name in names:  # padding, or a duplicate: the first one wins
            continue
        if datatype not in datatypes:
            raise CloudFormatError(f"field {name!r} has unknown datatype {datatype}")
        base = np.dtype(order + datatypes[datatype])
        count = max(int(count), 1)
        if offset + base.itemsize * count > point_step:
            raise CloudFormatError(
                f"field {name!r} (offset {offset}, {count} x {base}) does not "
                f"fit in a point of {point_step} bytes"
            )
        names.append(name)
        offsets.append(int(offset))
        formats.append(base if count == 1 else (base, (count,)))
    if not names:
        raise CloudFormatError("the cloud declares no fields")
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": int(point_step)}
    )


def _view(data, dtype: np.dtype, height: int, width: int, row_step: int) -> np.ndarray:
    """A 1-D view of `data` as height*width points; rows may be padded (row_step).

    The data must hold exactly the points the header declares: `height * row_step` bytes (or
    that without the last row's padding). Anything else means a damaged header or damaged
    data, and points would silently go missing or be invented.
    """
    n = height * width
    step = dtype.itemsize
    if n == 0:
        if len(data):
            raise CloudFormatError(
                f"height {height} x width {width} declares no points, but "
                f"the cloud carries {len(data)} bytes of data"
            )
        return np.empty(0, dtype)
    row_step = row_step or width * step
    if row_step < width * step:
        raise CloudFormatError(f"row_step {row_step} < width {width} x point_step {step}")
    need = (height - 1) * row_step + width * step
    if len(data) not in (need, height * row_step):
        raise CloudFormatError(
            f"data has {len(data)} bytes; height {height} x row_step "
            f"{row_step} (width {width} x point_step {step}) needs "
            f"{height * row_step}"
        )
    if height == 1 or row_step == width * step:
        return np.frombuffer(data, dtype=dtype, count=n)
    rows = np.ndarray((height, width), dtype, buffer=data, strides=(row_step, step))
    return rows.reshape(-1)  # copies: padded rows cannot be one flat view


def ros_cloud_to_array(msg: Any) -> np.ndarray:
    """A decoded ROS PointCloud2 (attribute access, `data` as bytes) -> 1-D structured array."""
    fields = [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    if not 0 < msg.point_step <= MAX_POINT_STEP:
        raise CloudFormatError(f"point_step {msg.point_step} is not in 1..{MAX_POINT_STEP}")
    dtype = fields_dtype(fields, msg.point_step, big_endian=bool(msg.is_bigendian))
    return _view(msg.data, dtype, int(msg.height), int(msg.width), int(msg.row_step))


def foxglove_cloud_to_array(msg: Any) -> np.ndarray:
    """A decoded foxglove.PointCloud (protobuf) -> 1-D structured array (always little-endian)."""
    if not 0 < msg.point_stride <= MAX_POINT_STEP:
        raise CloudFormatError(f"point_stride {msg.point_stride} is not in 1..{MAX_POINT_STEP}")
    fields = [(f.name, f.offset, f.type, 1) for f in msg.fields]
    dtype = fields_dtype(fields, msg.point_stride, datatypes=FOXGLOVE_DATATYPES)
    if len(msg.data) % msg.point_stride:
        raise CloudFormatError(
            f"data length {len(msg.data)} is not a multiple of the point stride {msg.point_stride}"
        )
    return np.frombuffer(msg.data, dtype=dtype)


def describe_fields(arr: np.ndarray) -> str:
    """'x:float32, y:float32, label:uint16[...]' — for error messages that list what a cloud has."""
    parts = []
    for name in arr.dtype.names:
        sub = arr.dtype.fields[name][0]
        base = sub.base if sub.shape else sub
        parts.append(f"{name}:{base.name}" + (f"[{sub.shape[0]}]" if sub.shape else ""))
    return ", ".join(parts)


def has_field(arr: np.ndarray, name: str) -> bool:
    return name in (arr.dtype.names or ())


def column(arr: np.ndarray, name: str) -> np.ndarray:
    """One field as a contiguous native-endian array: (N,) or (N, count)."""
    if not has_field(arr, name):
        raise CloudFormatError(f"the cloud has no field {name!r}; it has: {describe_fields(arr)}")
    values = arr[name]
    return np.ascontiguousarray(values, dtype=values.dtype.newbyteorder("="))


def xyz(arr: np.ndarray) -> np.ndarray:
    """(N, 3) float32 contiguous points.

    When x, y, z are consecutive float32 (the usual layout) one strided view and one copy do
    it; otherwise each column is gathered separately.
    """
    for name in ("x", "y", "z"):
        if not has_field(arr, name):
            raise CloudFormatError(
                f"the cloud has no {name!r} field; it has: {describe_fields(arr)}"
            )
    fx, ox = arr.dtype.fields["x"][:2]
    fy, oy = arr.dtype.fields["y"][:2]
    fz, oz = arr.dtype.fields["z"][:2]
    if fx == fy == fz and fx.kind == "f" and fx.itemsize == 4 and oy == ox + 4 and oz == ox + 8:
        view = (
            np.ndarray(
                (arr.shape[0], 3), fx, buffer=arr, offset=ox, strides=(arr.dtype.itemsize, 4)
            )
            if arr.shape[0]
            else np.empty((0, 3), fx)
        )
        return np.ascontiguousarray(view, dtype=np.float32)
    return np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float32)


def check_used_fields(arr: np.ndarray, names: Iterable[str]) -> None:
    """The fields a reader uses must be single numbers (x, y, z) and must not overlap each
    other: overlapping fields mean a damaged layout, whose values would be garbage."""
    spans = {}
    for name in dict.fromkeys(names):
        if not has_field(arr, name):
            continue
        sub, offset = arr.dtype.fields[name][:2]
        if name in ("x", "y", "z") and sub.shape:
            raise CloudFormatError(
                f"field {name!r} has {sub.shape[0]} values per point; a coordinate has one"
            )
        spans[name] = (offset, offset + sub.itemsize)
    for a_name, (a0, a1) in spans.items():
        for b_name, (b0, b1) in spans.items():
            if a_name < b_name and a0 < b1 and b0 < a1:
                raise CloudFormatError(
                    f"fields {a_name!r} (bytes {a0}-{a1}) and {b_name!r} (bytes {b0}-{b1}) overlap"
                )


LABEL_LIMIT = 2**32  # labels are uint32 (SemanticKITTI: semantic id + instance)


def integer_labels(values: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(labels as int64, invalid mask). Float fields are accepted; a value that is not a whole
    number in [0, 2^32) (NaN, inf, 1e300, 0.5, -1) is invalid: 0 there, for the caller to count
    as unknown."""
    if values.ndim != 1:
        raise CloudFormatError(
            f"label field {name!r} has {values.shape[1]} values per point; "
            f"a label field has one (use a probability field for several)"
        )
    if values.dtype.kind in "iu":
        return values.astype(np.int64), np.zeros(len(values), bool)
    if values.dtype.kind == "f":
        with np.errstate(invalid="ignore"):
            invalid = ~((values >= 0) & (values < LABEL_LIMIT) & (values == np.floor(values)))
        return np.where(invalid, 0, values).astype(np.int64), invalid
    raise CloudFormatError(f"label field {name!r} has unsupported type {values.dtype}")


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colours -> (N,) float32 `rgb` as PCL and RViz read it: the bits of the
    uint32 0x00RRGGBB viewed as a float32 (RViz: Color Transformer "RGB8")."""
    rgb = np.asarray(rgb, dtype=np.uint32)
    packed = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    return packed.astype("<u4").view("<f4")


def unpack_rgb(values: np.ndarray) -> np.ndarray:
    """(N,) packed float32 `rgb` -> (N, 3) uint8 (the inverse of `pack_rgb`)."""
    bits = np.ascontiguousarray(values, dtype="<f4").view("<u4")
    return np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF], 1).astype(np.uint8)


# ---- writing -------------------------------------------------------------------------------


def _fields_of(dtype: np.dtype, datatypes: dict):
    """(name, offset, datatype code, count) per field of a structured dtype, and its byte order."""
    codes = {v: k for k, v in datatypes.items()}
    out, orders = [], set()
    for name in dtype.names:
        sub, offset = dtype.fields[name][:2]
        base = sub.base if sub.shape else sub
        count = int(np.prod(sub.shape)) if sub.shape else 1
        key = base.kind + str(base.itemsize)
        if key not in codes:
            raise CloudFormatError(f"field {name!r}: {base} has no point-field datatype")
        if base.itemsize > 1:
            orders.add(
                base.byteorder if base.byteorder in "<>" else ("<" if np.little_endian else ">")
            )
        out.append((name, int(offset), codes[key], count))
    if len(orders) > 1:
        raise CloudFormatError("fields mix byte orders")
    return out, orders.pop() if orders else "<"


def array_to_ros_cloud(arr: np.ndarray, frame_id: str, stamp_ns: int) -> dict:
    """A 1-D structured array -> PointCloud2 as the plain dict `mcap_ros2` encodes.

    Padding and field order come from the dtype (offsets, itemsize); a big-endian dtype gives
    `is_bigendian = true`.
    """
    arr = np.ascontiguousarray(arr)
    fields, order = _fields_of(arr.dtype, ROS_DATATYPES)
    return {
        "header": {"stamp": ros_time(stamp_ns), "frame_id": frame_id},
        "height": 1,
        "width": int(arr.shape[0]),
        "fields": [{"name": n, "offset": o, "datatype": d, "count": c} for n, o, d, c in fields],
        "is_bigendian": order == ">",
        "point_step": arr.dtype.itemsize,
        "row_step": arr.dtype.itemsize * arr.shape[0],
        "data": arr.tobytes(),
        "is_dense": bool(
            all(np.all(np.isfinite(arr[n])) for n in ("x", "y", "z") if has_field(arr, n))
        ),
    }


def array_to_foxglove_cloud(
    arr: np.ndarray, frame_id: str, stamp_ns: int, T_frame_cloud: np.ndarray | None = None
) -> PointCloud:
    """A 1-D structured array -> foxglove.PointCloud (protobuf). Little-endian only (Foxglove
    reads nothing else); `T_frame_cloud` is the cloud origin in `frame_id` (the `pose` field)."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from foxglove_schemas_protobuf.Pose_pb2 import Pose
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
    from google.protobuf.timestamp_pb2 import Timestamp

    from tisem.io.tf import matrix_to_quat

    arr = np.ascontiguousarray(arr)
    fields, order = _fields_of(arr.dtype, FOXGLOVE_DATATYPES)
    if order != "<" or any(c != 1 for *_, c in fields):
        raise CloudFormatError("foxglove.PointCloud needs little-endian fields with count 1")
    T = np.eye(4) if T_frame_cloud is None else np.asarray(T_frame_cloud, dtype=np.float64)
    q = matrix_to_quat(T[:3, :3])
    sec, nanos = split_ns(stamp_ns)
    return PointCloud(
        timestamp=Timestamp(seconds=sec, nanos=nanos),
        frame_id=frame_id,
        pose=Pose(
            position=Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
        point_stride=arr.dtype.itemsize,
        fields=[PackedElementField(name=n, offset=o, type=d) for n, o, d, _ in fields],
        data=arr.tobytes(),
    )
