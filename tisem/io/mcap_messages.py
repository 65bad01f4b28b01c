"""MCAP messages -> what tisem needs from them: which schemas it reads, one decoder per channel,
the points of a cloud message and the transforms a pose message carries.

ROS 2 messages (`cdr`) and Foxglove ones (protobuf) are decoded by the `mcap-ros2-support` and
`mcap-protobuf-support` factories; everything after decoding is plain attribute access, so the
functions here take either kind.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from mcap.records import Channel, Schema

from tisem.errors import ScanError
from tisem.io import pointcloud2 as pc2
from tisem.io.stamps import stamp_to_ns
from tisem.io.tf import make_transform
from tisem.labels import to_train_ids

PROBABILITY_SLACK = 1e-3  # rounding in a network's softmax may leave a value just above 1

CLOUD_SCHEMAS = ("sensor_msgs/msg/PointCloud2", "foxglove.PointCloud")
# point-cloud-like schemas we recognise but cannot map, to say so instead of "no cloud topic"
UNSUPPORTED_CLOUDS = (
    "sensor_msgs/PointCloud2",
    "foxglove.CompressedPointCloud",
    "sensor_msgs/msg/LaserScan",
    "foxglove.LaserScan",
)
# schema names of the pose carriers: transform trees, and single poses (`--pose-topic`)
# (tf/tfMessage: tf before tf2, in the ROS 1 bags of older releases; the same fields)
TF_MESSAGES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
TF_SCHEMAS = (*TF_MESSAGES, "foxglove.FrameTransform", "foxglove.FrameTransforms")
POSE_SCHEMAS = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)


class MessageDecoders:
    """One decode function per channel, from the ROS 2 and protobuf decoder factories."""

    def __init__(self) -> None:
        from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoders
        from mcap_ros2.decoder import DecoderFactory as Ros2Decoders

        self._factories = [Ros2Decoders(), ProtobufDecoders()]
        self._cache: dict[int, object] = {}

    def decode(self, channel: Channel, schema: Schema | None, data: bytes) -> Any:
        """The decoded message (attribute access); `ScanError` when no factory can decode it."""
        fn = self._cache.get(channel.id)
        if fn is None:
            for factory in self._factories:
                fn = factory.decoder_for(channel.message_encoding, schema)
                if fn is not None:
                    break
            else:
                raise ScanError(
                    f"no decoder for {channel.message_encoding!r} messages with "
                    f"schema {schema.encoding if schema else None!r} on "
                    f"{channel.topic}"
                )
            self._cache[channel.id] = fn
        return fn(data)


def _xyz(v) -> tuple:
    return (v.x, v.y, v.z)


def _xyzw(q) -> tuple:
    return (q.x, q.y, q.z, q.w)


def _protobuf_quat(q) -> tuple:
    """A protobuf quaternion left unset decodes as all zeros: that means the identity."""
    xyzw = _xyzw(q)
    return xyzw if any(xyzw) else (0, 0, 0, 1)


def cloud_parts(schema_name: str, msg: Any) -> tuple[np.ndarray, str, int, np.ndarray | None]:
    """(structured points, frame_id, stamp_ns, T_frame_cloud) of a decoded cloud message.

    T_frame_cloud is a foxglove.PointCloud's `pose` (the cloud's origin in its frame); a
    PointCloud2 has none (None).
    """
    if schema_name == "foxglove.PointCloud":
        p = msg.pose.position
        return (
            pc2.foxglove_cloud_to_array(msg),
            msg.frame_id,
            stamp_to_ns(msg.timestamp),
            make_transform((p.x, p.y, p.z), _protobuf_quat(msg.pose.orientation)),
        )
    return pc2.ros_cloud_to_array(msg), msg.header.frame_id, stamp_to_ns(msg.header.stamp), None


def pose_edges(
    schema_name: str, msg: Any, *, default_parent: str, default_child: str | None
) -> list[tuple]:
    """(parent, child, stamp_ns, xyz, quat) tuples carried by one decoded pose message.

    Odometry names its child (`child_frame_id`); PoseStamped does not, so `default_child` (the
    frame the user says the pose is of) is used; empty parents mean `default_parent`.
    """
    if schema_name in TF_MESSAGES:
        return [
            (
                t.header.frame_id,
                t.child_frame_id,
                stamp_to_ns(t.header.stamp),
                _xyz(t.transform.translation),
                _xyzw(t.transform.rotation),
            )
            for t in msg.transforms
        ]
    if schema_name in ("foxglove.FrameTransform", "foxglove.FrameTransforms"):
        transforms = [msg] if schema_name == "foxglove.FrameTransform" else list(msg.transforms)
        return [
            (
                t.parent_frame_id,
                t.child_frame_id,
                stamp_to_ns(t.timestamp),
                _xyz(t.translation),
                _protobuf_quat(t.rotation),
            )
            for t in transforms
        ]
    if schema_name in POSE_SCHEMAS:
        pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
        child = getattr(msg, "child_frame_id", "") or default_child
        parent = msg.header.frame_id or default_parent
        return [
            (
                parent,
                child,
                stamp_to_ns(msg.header.stamp),
                _xyz(pose.position),
                _xyzw(pose.orientation),
            )
        ]
    raise ValueError(f"{schema_name} is not a pose message tisem understands")


def cloud_labels(
    arr: np.ndarray, field_name: str, label_space: str, num_classes: int, either: str = "raw"
) -> tuple[np.ndarray, int, str]:
    """Train ids of a cloud's label field, how many points had an unknown or invalid label
    (those become 0, no evidence), and the space the values were read in ("raw" or "train").
    `label_space`: raw SemanticKITTI ids, train ids, or "auto" (`tisem.labels.to_train_ids`,
    with `either`)."""
    values, invalid = pc2.integer_labels(pc2.column(arr, field_name), field_name)
    # an invalid value is 0 in `values`: unlabeled in either space, and counted once here
    train, unknown, space = to_train_ids(values, label_space, num_classes, either)
    return train, unknown + int(np.count_nonzero(invalid)), space


def cloud_probabilities(
    arr: np.ndarray, field_name: str, num_classes: int
) -> tuple[np.ndarray, int]:
    """(N, C) float32 probabilities of a count=C field; a point with a value that is no
    probability (NaN, inf, negative, above 1) gets a zero row, no evidence, and is counted."""
    probs = pc2.column(arr, field_name)
    if probs.ndim != 2 or probs.shape[1] != num_classes:
        per = 1 if probs.ndim == 1 else probs.shape[1]
        raise pc2.CloudFormatError(
            f"probability field {field_name!r} has {per} value(s) per "
            f"point; the map has {num_classes} classes"
        )
    if probs.dtype.kind != "f":
        raise pc2.CloudFormatError(
            f"probability field {field_name!r} has type {probs.dtype}, not a floating-point type"
        )
    with np.errstate(invalid="ignore"):
        bad = ~np.all((probs >= 0) & (probs <= 1 + PROBABILITY_SLACK), axis=1)  # NaN too
    probs = probs.astype(np.float32)
    probs[bad] = 0.0
    return probs, int(np.count_nonzero(bad))
