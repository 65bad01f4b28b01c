"""Message stamps <-> integer nanoseconds: the one clock of every MCAP reader and writer.

Stamps are kept as integer nanoseconds (never float seconds), so equal stamps compare exactly
and a transform sampled at a cloud's stamp is found at that very stamp. The two carriers:
ROS 2 `builtin_interfaces/Time` (`sec`, `nanosec`) and protobuf `google.protobuf.Timestamp`
(`seconds`, `nanos`, what Foxglove schemas use).
"""
from __future__ import annotations

from typing import Any

NS_PER_S = 1_000_000_000


def stamp_to_ns(stamp: Any) -> int:
    """A decoded ROS 2 Time or protobuf Timestamp -> integer nanoseconds.

    ValueError when the stamp does not fit in 64-bit nanoseconds (a protobuf `seconds` is an
    int64, so a damaged one can be anything): numpy keeps stamps as int64."""
    if hasattr(stamp, "nanosec"):
        ns = int(stamp.sec) * NS_PER_S + int(stamp.nanosec)
    else:
        ns = int(stamp.seconds) * NS_PER_S + int(stamp.nanos)
    if not -2 ** 63 <= ns < 2 ** 63:
        raise ValueError(f"the stamp ({ns / NS_PER_S:.6g} s) does not fit in 64-bit nanoseconds")
    return ns


def split_ns(stamp_ns: int) -> tuple[int, int]:
    """Integer nanoseconds -> (whole seconds, nanoseconds within the second)."""
    return divmod(int(stamp_ns), NS_PER_S)


def ros_time(stamp_ns: int) -> dict:
    """Integer nanoseconds -> a `builtin_interfaces/Time` as the dict `mcap_ros2` encodes."""
    sec, nanosec = split_ns(stamp_ns)
    return {"sec": sec, "nanosec": nanosec}


def seconds_to_ns(stamp_s: float) -> int:
    """Float seconds (a `Scan.stamp_s`) -> the nearest integer nanosecond."""
    return int(round(stamp_s * 1e9))
