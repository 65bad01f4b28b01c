"""Writing MCAP: the semantic map for Foxglove, and ROS 2 recordings the way rosbag2 writes them.

`write_map_mcap` puts the map as one `foxglove.PointCloud` (protobuf) of voxel centres in the map
frame, with `red green blue alpha` uint8 fields (Foxglove then colours by "RGBA (separate
fields)" on its own), the train id `label` and its `probability`; the class table goes in a
metadata record. With `scans`, each input scan follows on its own topic, its points in the
sensor frame and its pose in the message's `pose` field, so it overlays the map without /tf.
The topics and the point layouts are `tisem.io.map_clouds`.

`Ros2McapWriter` writes `cdr` messages with rosbag2's schema texts (rosbag2 spells
dependencies `MSG: std_msgs/Header`; Rerun resolves only that spelling) and exposes the choices
rosbag2 presets make: compression, chunk CRCs, chunking, indexes/summary. Tests use the last
ones to produce the unindexed and CRC-less files found in the wild.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterable
from pathlib import Path
from typing import BinaryIO

import numpy as np
import zstandard
from mcap.well_known import SchemaEncoding
from mcap.writer import CompressionType, IndexType
from mcap.writer import Writer as McapWriter

# The encoder generator of mcap-ros2-support; its own Writer hard-codes the MCAP options
# (always indexed, always chunked), which rosbag2 presets and our damage tests need to vary.
from mcap_ros2._dynamic import serialize_dynamic

from tisem.io.map_clouds import (
    DYNAMIC_MAP_TOPIC,
    DYNAMIC_POINTS_TOPIC,
    MAP_TOPIC,
    SCANS_TOPIC,
    map_points,
    scan_clouds,
    scan_points,
)
from tisem.io.pointcloud2 import array_to_foxglove_cloud, array_to_ros_cloud
from tisem.io.stamps import map_stamp_ns, ros_time, scan_stamp_ns
from tisem.io.tf import matrix_to_quat
from tisem.labels import class_table
from tisem.scan import Scan
from tisem.snapshot import MapSnapshot

__all__ = [
    "COMPRESSION",
    "Ros2McapWriter",
    "ros2_msgdef",
    "transform_stamped",
    "pose_msg",
    "write_map_mcap",
    # the topics and point layouts of the map file (`tisem.io.map_clouds`)
    "MAP_TOPIC",
    "SCANS_TOPIC",
    "DYNAMIC_MAP_TOPIC",
    "DYNAMIC_POINTS_TOPIC",
    "map_points",
    "scan_points",
    "scan_clouds",
]

COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}

# ---- ROS 2 message definitions, as rosbag2 stores them -------------------------------------

_SEPARATOR = "=" * 80 + "\n"
_DEPENDENCIES = {
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "sensor_msgs/PointField": (
        "uint8 INT8    = 1\nuint8 UINT8   = 2\nuint8 INT16   = 3\nuint8 UINT16  = 4\n"
        "uint8 INT32   = 5\nuint8 UINT32  = 6\nuint8 FLOAT32 = 7\nuint8 FLOAT64 = 8\n"
        "string name\nuint32 offset\nuint8  datatype\nuint32 count\n"
    ),
    "geometry_msgs/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\nTransform transform\n"
    ),
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/Twist": "Vector3  linear\nVector3  angular\n",
    "geometry_msgs/TwistWithCovariance": "Twist twist\nfloat64[36] covariance\n",
}
_MESSAGES = {
    "sensor_msgs/msg/PointCloud2": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\n"
        "bool    is_bigendian\nuint32  point_step\nuint32  row_step\nuint8[] data\nbool is_dense\n",
        ["std_msgs/Header", "builtin_interfaces/Time", "sensor_msgs/PointField"],
    ),
    "tf2_msgs/msg/TFMessage": (
        "geometry_msgs/TransformStamped[] transforms\n",
        [
            "geometry_msgs/TransformStamped",
            "std_msgs/Header",
            "builtin_interfaces/Time",
            "geometry_msgs/Transform",
            "geometry_msgs/Vector3",
            "geometry_msgs/Quaternion",
        ],
    ),
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n",
        [
            "std_msgs/Header",
            "builtin_interfaces/Time",
            "geometry_msgs/PoseWithCovariance",
            "geometry_msgs/Pose",
            "geometry_msgs/Point",
            "geometry_msgs/Quaternion",
            "geometry_msgs/TwistWithCovariance",
            "geometry_msgs/Twist",
            "geometry_msgs/Vector3",
        ],
    ),
    "geometry_msgs/msg/PoseStamped": (
        "std_msgs/Header header\nPose pose\n",
        [
            "std_msgs/Header",
            "builtin_interfaces/Time",
            "geometry_msgs/Pose",
            "geometry_msgs/Point",
            "geometry_msgs/Quaternion",
        ],
    ),
}


def ros2_msgdef(type_name: str) -> str:
    """The concatenated `ros2msg` schema text of a message type, rosbag2 style."""
    text, deps = _MESSAGES[type_name]
    return text + "".join(f"{_SEPARATOR}MSG: {d}\n{_DEPENDENCIES[d]}" for d in deps)


def transform_stamped(parent: str, child: str, stamp_ns: int, T_parent_child: np.ndarray) -> dict:
    T = np.asarray(T_parent_child, dtype=np.float64)
    q = matrix_to_quat(T[:3, :3])
    return {
        "header": {"stamp": ros_time(stamp_ns), "frame_id": parent},
        "child_frame_id": child,
        "transform": {
            "translation": dict(zip("xyz", map(float, T[:3, 3]))),
            "rotation": dict(zip("xyzw", map(float, q))),
        },
    }


def pose_msg(T: np.ndarray) -> dict:
    q = matrix_to_quat(np.asarray(T)[:3, :3])
    return {
        "position": dict(zip("xyz", map(float, np.asarray(T)[:3, 3]))),
        "orientation": dict(zip("xyzw", map(float, q))),
    }


class Ros2McapWriter:
    """A ROS 2 (profile `ros2`, `cdr`) MCAP writer with rosbag2's schema texts.

    compression: zstd | lz4 | none. crcs=False, chunked=False and indexed=False reproduce
    rosbag2's presets (no chunk CRC; `fastwrite`: no chunks; no summary at all).
    zstd_messages: each message's data a zstd frame of its own, as rosbag2's per-message
    compression writes it (give compression "none": rosbag2 leaves its chunks uncompressed
    then; a reader learns of it from the folder's metadata.yaml).
    """

    def __init__(
        self,
        output: str | Path | BinaryIO,
        *,
        compression: str = "zstd",
        chunk_size: int = 1 << 20,
        crcs: bool = True,
        chunked: bool = True,
        indexed: bool = True,
        zstd_messages: bool = False,
    ) -> None:
        if compression not in COMPRESSION:
            raise ValueError(
                f"compression must be one of {sorted(COMPRESSION)}, got {compression!r}"
            )
        self._file = open(output, "wb") if isinstance(output, (str, Path)) else None
        self._writer = McapWriter(
            self._file or output,
            chunk_size=chunk_size,
            compression=COMPRESSION[compression],
            enable_crcs=crcs,
            use_chunking=chunked,
            index_types=IndexType.ALL if indexed else IndexType.NONE,
            repeat_channels=indexed,
            repeat_schemas=indexed,
            use_statistics=indexed,
            use_summary_offsets=indexed,
        )
        self._writer.start(profile="ros2", library="tisem")
        self._zstd = zstandard.ZstdCompressor() if zstd_messages else None
        self._schemas: dict[str, tuple[int, object]] = {}  # type -> (schema id, encoder)
        self._channels: dict[str, int] = {}
        # topic -> the metadata of its Channel record (rosbag2: `offered_qos_profiles`)
        self.channel_metadata: dict[str, dict[str, str]] = {}

    def write(
        self,
        topic: str,
        type_name: str,
        message: dict,
        log_time_ns: int,
        publish_time_ns: int | None = None,
        sequence: int = 0,
    ) -> None:
        if type_name not in self._schemas:
            text = ros2_msgdef(type_name)
            schema_id = self._writer.register_schema(type_name, SchemaEncoding.ROS2, text.encode())
            self._schemas[type_name] = (schema_id, serialize_dynamic(type_name, text)[type_name])
        schema_id, encode = self._schemas[type_name]
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(
                topic, "cdr", schema_id, self.channel_metadata.get(topic, {})
            )
        data = encode(message)
        self._writer.add_message(
            self._channels[topic],
            log_time=int(log_time_ns),
            publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
            sequence=sequence,
            data=data if self._zstd is None else self._zstd.compress(data),
        )

    def write_cloud(
        self,
        topic: str,
        points: np.ndarray,
        frame_id: str,
        stamp_ns: int,
        log_time_ns: int,
        sequence: int = 0,
    ) -> None:
        """`points`: a 1-D structured array (its dtype fixes fields, padding and byte order)."""
        self.write(
            topic,
            "sensor_msgs/msg/PointCloud2",
            array_to_ros_cloud(points, frame_id, stamp_ns),
            log_time_ns,
            sequence=sequence,
        )

    def write_transforms(
        self,
        transforms: list[tuple[str, str, int, np.ndarray]],
        log_time_ns: int,
        static: bool = False,
    ) -> None:
        """(parent, child, stamp_ns, T_parent_child) tuples as one TFMessage on /tf(_static)."""
        self.write(
            "/tf_static" if static else "/tf",
            "tf2_msgs/msg/TFMessage",
            {"transforms": [transform_stamped(*t) for t in transforms]},
            log_time_ns,
        )

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, data)

    def finish(self) -> None:
        self._writer.finish()
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> Ros2McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()


# ---- the map ---------------------------------------------------------------------------------


def write_map_mcap(
    path: str | Path,
    snapshot: MapSnapshot,
    frame_id: str = "map",
    scans: Iterable[tuple[Scan, np.ndarray]] | None = None,
    *,
    compression: str = "zstd",
    stamp_ns: int | None = None,
    dynamic: MapSnapshot | None = None,
) -> dict:
    """Write the map (and optionally the scans with their mapped labels) as an MCAP file.
    `dynamic` (free space): the voxels seen through, on DYNAMIC_MAP_TOPIC beside the map.

    scans: (Scan, mapped train ids) pairs, e.g. re-read and queried after mapping, or
    (Scan, mapped, dynamic flags) triples whose flagged points also go to DYNAMIC_POINTS_TOPIC
    (flags None: none); they may be a generator, written as they come. The map message is
    logged at `stamp_ns`, by default the first scan's stamp (Foxglove shows a message once
    playback reaches it, so the map is there from the start), or the last voxel update when
    there are no scans. Returns what was written: {"path", "voxels", "dynamic_voxels",
    "scans", "dynamic_scans", "map_topic", "scans_topic"}.
    """
    from mcap_protobuf.writer import Writer

    scans = iter(scans) if scans is not None else iter(())
    first = next(scans, None)
    if stamp_ns is None:
        stamp_ns = map_stamp_ns(snapshot, first[0] if first is not None else None)
    stamp_ns = max(int(stamp_ns), 0)
    n_scans = n_dynamic = 0
    with open(path, "wb") as f:
        writer = Writer(f, compression=COMPRESSION[compression])
        writer.add_metadata(
            "semantic_classes", {str(r["train_id"]): json.dumps(r) for r in class_table()}
        )
        writer.add_metadata(
            "tisem_map",
            {
                "frame_id": frame_id,
                "resolution_m": repr(float(snapshot.resolution_m)),
                "voxels": str(len(snapshot)),
                "map_topic": MAP_TOPIC,
                "label": "train id (see semantic_classes)",
                "probability": "normalised semantic counter of the label",
            },
        )
        layers = [(MAP_TOPIC, snapshot)]
        if dynamic is not None:
            layers.append((DYNAMIC_MAP_TOPIC, dynamic))
        for topic, layer in layers:
            writer.write_message(
                topic,
                array_to_foxglove_cloud(map_points(layer), frame_id, stamp_ns),
                log_time=stamp_ns,
                publish_time=stamp_ns,
            )
        for item in itertools.chain([first] if first is not None else [], scans):
            scan, mapped, flags = (*item, None)[:3]
            t = max(scan_stamp_ns(scan), 0)
            clouds = scan_clouds(scan, scan_points(scan, mapped), flags)
            n_dynamic += len(clouds) - 1
            for topic, cloud in clouds:
                writer.write_message(
                    topic,
                    array_to_foxglove_cloud(cloud, frame_id, t, T_frame_cloud=scan.T_world_sensor),
                    log_time=t,
                    publish_time=t,
                    sequence=scan.index,
                )
            n_scans += 1
        writer.finish()
    return {
        "path": str(path),
        "voxels": len(snapshot),
        "dynamic_voxels": 0 if dynamic is None else len(dynamic),
        "scans": n_scans,
        "dynamic_scans": n_dynamic,  # scans with points on DYNAMIC_POINTS_TOPIC
        "map_topic": MAP_TOPIC,
        "scans_topic": SCANS_TOPIC,
    }
