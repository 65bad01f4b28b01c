"""A synthetic ROS 2 recording: labelled clouds, /tf and /tf_static, the way rosbag2 logs them.

For the MCAP reader's tests, the decode benchmark and trying the tools without data. It is
deliberately simpler than the street world of `tisem.synth.sequence`, because what it checks
needs properties that world does not have:
- the motion is analytic (constant velocity, constant yaw rate), so a pose interpolated between
  /tf samples (linear in translation, slerp in rotation) equals the truth to 1e-9 at any stamp,
  rotation included;
- a cloud has exactly `n_points` points with any label type and extra fields, so tests can size
  chunks to hold one cloud each and count what a damaged file loses, and the benchmark can
  ask for 120,000 points per scan;
- a cloud costs milliseconds (geometry from beam angles, no ray casting).
Its labels are the street world's raw SemanticKITTI ids.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from tisem.io.mcap_writer import Ros2McapWriter
from tisem.io.pointcloud2 import array_to_ros_cloud
from tisem.synth.scene import BUILDING, CAR, POLE, ROAD, SIDEWALK, VEGETATION

# the sensor mount of the synthetic log: 1.2 m up, 0.3 m forward, yawed 90 degrees and tilted 2
_MOUNT = np.array(
    [[0.0, -1.0, 0.0, 0.3], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.2], [0.0, 0.0, 0.0, 1.0]]
)
_TILT = np.array(
    [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, np.cos(0.035), -np.sin(0.035), 0.0],
        [0.0, np.sin(0.035), np.cos(0.035), 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
T_BASE_LIDAR = _MOUNT @ _TILT

SCAN_PERIOD_NS = 100_000_000  # clouds at 10 Hz ...
SCAN_OFFSET_NS = 13_000_000  # ... stamped between the /tf samples
RECEIVE_LAG_NS = 35_000_000  # a recorder logs a cloud when it arrives, after its stamp


def synthetic_pose(t_s: float, speed_mps: float = 5.0, yaw_rate: float = 0.2) -> np.ndarray:
    """T_map_base_link: constant velocity along map x and a constant yaw rate (analytic, so
    interpolated lookups can be checked exactly)."""
    c, s = np.cos(yaw_rate * t_s), np.sin(yaw_rate * t_s)
    return np.array([[c, -s, 0, speed_mps * t_s], [s, c, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def synthetic_points(
    n_points: int, rng: np.random.Generator, label_dtype: str = "<u2", extra_fields: tuple = ()
) -> np.ndarray:
    """A ring-structured scan (64 beams) with raw SemanticKITTI labels derived from geometry:
    road below the sensor, building far away, vegetation between, car nearby."""
    fields = [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("intensity", "<f4"),
        ("label", label_dtype),
        *extra_fields,
    ]
    arr = np.zeros(n_points, np.dtype(fields))
    beam = np.arange(n_points) % 64
    azimuth = np.linspace(0, 2 * np.pi, n_points, endpoint=False)
    elevation = np.deg2rad(-25 + 28 * beam / 63)
    rng_m = np.clip(1.7 / np.maximum(np.tan(-elevation), 0.03), 3, 60)
    rng_m *= 1 + 0.01 * rng.standard_normal(n_points)
    arr["x"] = rng_m * np.cos(elevation) * np.cos(azimuth)
    arr["y"] = rng_m * np.cos(elevation) * np.sin(azimuth)
    arr["z"] = rng_m * np.sin(elevation)
    arr["intensity"] = rng.random(n_points)
    # classes by geometry, with 5 % of the labels flipped (a network's noise)
    raw = np.where(
        arr["z"] < -1.5,
        np.where(np.sin(azimuth * 3) > 0.6, SIDEWALK, ROAD),
        np.where(rng_m > 40, BUILDING, np.where(rng_m < 8, CAR, VEGETATION)),
    )
    noise = rng.random(n_points) < 0.05
    raw[noise] = rng.choice([CAR, ROAD, SIDEWALK, BUILDING, VEGETATION, POLE], int(noise.sum()))
    arr["label"] = raw
    return arr


def write_synthetic_log(
    path: str | Path,
    n_scans: int = 5,
    n_points: int = 2000,
    *,
    compression: str = "zstd",
    crcs: bool = True,
    chunked: bool = True,
    indexed: bool = True,
    chunk_size: int = 1 << 20,
    seed: int = 0,
    label_dtype: str = "<u2",
    tf_rate_hz: float = 50.0,
    t0_s: float = 100.0,
    tf_end_s: float | None = None,
    topic: str = "/velodyne_points",
    frame_id: str = "velodyne",
    data_crc: bool = False,
    cloud_hook: Callable[[int, dict], dict] | None = None,
    zstd_messages: bool = False,
) -> dict:
    """A small ROS 2 recording: /tf_static base_link->velodyne (non-identity), /tf
    map->base_link at `tf_rate_hz` from `synthetic_pose`, clouds at 10 Hz whose header stamps
    fall between tf samples and whose log times lag by 35 ms (a recorder's receive time).
    `tf_end_s` (seconds after the start) stops /tf early: later scans have no pose. The
    writer options (compression, crcs, chunked, indexed, chunk_size) are `Ros2McapWriter`'s;
    `zstd_messages` compresses each message on its own (rosbag2's per-message compression);
    `data_crc` also fills in the data section's CRC (the data-end record), which an unchunked
    file needs to have any CRC at all. `cloud_hook(i, message)` may change the PointCloud2
    message of scan i (a dict, as `array_to_ros_cloud` makes it) before it is written: clouds
    whose layout fields disagree with their data, for the damage tests; `truth` keeps the
    points as generated.

    Returns the truth: {"stamps_ns", "T_world_sensor" (K,4,4), "points" [structured arrays]}.
    """
    rng = np.random.default_rng(seed)
    t0 = int(t0_s * 1e9)
    scan_stamps = [t0 + SCAN_OFFSET_NS + i * SCAN_PERIOD_NS for i in range(n_scans)]
    t_end = scan_stamps[-1] + SCAN_PERIOD_NS if n_scans else t0
    if tf_end_s is not None:
        t_end = min(t_end, t0 + int(tf_end_s * 1e9))
    tf_stamps = list(range(t0, t_end + 1, int(1e9 / tf_rate_hz)))
    # (log time, 0 = /tf or 1 = cloud, scan index): a /tf sample logged at the same time as a
    # cloud comes first
    events = [(t, 0, None) for t in tf_stamps] + [
        (t + RECEIVE_LAG_NS, 1, i) for i, t in enumerate(scan_stamps)
    ]
    truth = {
        "stamps_ns": scan_stamps,
        "points": [],
        "T_world_sensor": np.array(
            [synthetic_pose((t - t0) / 1e9) @ T_BASE_LIDAR for t in scan_stamps]
        ).reshape(-1, 4, 4),
    }
    with Ros2McapWriter(
        path,
        compression=compression,
        crcs=crcs,
        chunked=chunked,
        indexed=indexed,
        chunk_size=chunk_size,
        zstd_messages=zstd_messages,
    ) as w:
        w.write_transforms([("base_link", frame_id, t0, T_BASE_LIDAR)], t0, static=True)
        for log_time, kind, i in sorted(events, key=lambda e: e[:2]):
            if kind == 0:
                w.write_transforms(
                    [("map", "base_link", log_time, synthetic_pose((log_time - t0) / 1e9))],
                    log_time,
                )
            else:
                arr = synthetic_points(n_points, rng, label_dtype)
                truth["points"].append(arr)
                msg = array_to_ros_cloud(arr, frame_id, scan_stamps[i])
                if cloud_hook is not None:
                    msg = cloud_hook(i, msg)
                w.write(topic, "sensor_msgs/msg/PointCloud2", msg, log_time, sequence=i)
    if data_crc:
        add_data_crc(path)
    return truth


def add_data_crc(path: str | Path) -> None:
    """Fill in the data-end record's CRC of all bytes before it (the Python writer leaves it 0
    unless asked). The summary that follows does not cover the data-end record, so nothing
    else changes."""
    data = bytearray(Path(path).read_bytes())
    pos = 8
    while data[pos] != 0x0F:  # the data-end record
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    struct.pack_into("<I", data, pos + 9, zlib.crc32(data[:pos]))
    Path(path).write_bytes(bytes(data))


def write_foxglove_log(
    path: str | Path,
    n_scans: int = 5,
    n_points: int = 2000,
    *,
    seed: int = 0,
    t0_s: float = 100.0,
    tf_rate_hz: float = 50.0,
    chunk_size: int = 1 << 20,
) -> dict:
    """The same drive as `write_synthetic_log` the way Foxglove tools log it (protobuf,
    zstd chunks with CRCs): `foxglove.FrameTransform` on /tf (the mount logged once, so it is
    taken as static) and `foxglove.PointCloud` on /lidar_top. Returns the truth likewise."""
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
    from google.protobuf.timestamp_pb2 import Timestamp
    from mcap_protobuf.writer import Writer

    from tisem.io.pointcloud2 import array_to_foxglove_cloud
    from tisem.io.stamps import split_ns
    from tisem.io.tf import matrix_to_quat

    def transform(parent: str, child: str, t: int, T: np.ndarray) -> FrameTransform:
        q = matrix_to_quat(T[:3, :3])
        sec, nanos = split_ns(t)
        return FrameTransform(
            timestamp=Timestamp(seconds=sec, nanos=nanos),
            parent_frame_id=parent,
            child_frame_id=child,
            translation=Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    rng = np.random.default_rng(seed)
    t0 = int(t0_s * 1e9)
    scan_stamps = [t0 + SCAN_OFFSET_NS + i * SCAN_PERIOD_NS for i in range(n_scans)]
    tf_stamps = range(t0, scan_stamps[-1] + SCAN_PERIOD_NS + 1, int(1e9 / tf_rate_hz))
    events = sorted(
        [(t, 0, None) for t in tf_stamps]
        + [(t + RECEIVE_LAG_NS, 1, i) for i, t in enumerate(scan_stamps)]
    )
    truth = {
        "stamps_ns": scan_stamps,
        "points": [],
        "T_world_sensor": np.array(
            [synthetic_pose((t - t0) / 1e9) @ T_BASE_LIDAR for t in scan_stamps]
        ).reshape(-1, 4, 4),
    }
    with open(path, "wb") as f, Writer(f, chunk_size=chunk_size) as w:
        w.write_message(
            "/tf",
            transform("base_link", "lidar_top", t0, T_BASE_LIDAR),
            log_time=t0,
            publish_time=t0,
        )
        for log_time, kind, i in events:
            if kind == 0:
                msg = transform("map", "base_link", log_time, synthetic_pose((log_time - t0) / 1e9))
                w.write_message("/tf", msg, log_time=log_time, publish_time=log_time)
            else:
                arr = synthetic_points(n_points, rng)
                truth["points"].append(arr)
                w.write_message(
                    "/lidar_top",
                    array_to_foxglove_cloud(arr, "lidar_top", scan_stamps[i]),
                    log_time=log_time,
                    publish_time=log_time,
                )
    return truth
