"""Message stamps <-> integer nanoseconds: the one clock of every MCAP reader and writer.

Stamps are kept as integer nanoseconds (never float seconds), so equal stamps compare exactly
and a transform sampled at a cloud's stamp is found at that very stamp. The two carriers:
ROS 2 `builtin_interfaces/Time` (`sec`, `nanosec`) and protobuf `google.protobuf.Timestamp`
(`seconds`, `nanos`, what Foxglove schemas use).
"""

from __future__ import annotations

from decimal import Decimal, InvalidOperation
from typing import Any

NS_PER_S = 1_000_000_000
# a whole number at least this big given as a start time is nanoseconds, not seconds: as
# seconds it would lie beyond the year 33000
NS_THRESHOLD = 10**12


def stamp_to_ns(stamp: Any) -> int:
    """A decoded ROS 2 Time or protobuf Timestamp -> integer nanoseconds.

    ValueError when the stamp does not fit in 64-bit nanoseconds (a protobuf `seconds` is an
    int64, so a damaged one can be anything): numpy keeps stamps as int64."""
    if hasattr(stamp, "nanosec"):
        ns = int(stamp.sec) * NS_PER_S + int(stamp.nanosec)
    else:
        ns = int(stamp.seconds) * NS_PER_S + int(stamp.nanos)
    if not -(2**63) <= ns < 2**63:
        raise ValueError(f"the stamp ({ns / NS_PER_S:.6g} s) does not fit in 64-bit nanoseconds")
    return ns


def split_ns(stamp_ns: int) -> tuple[int, int]:
    """Integer nanoseconds -> (whole seconds, nanoseconds within the second)."""
    return divmod(int(stamp_ns), NS_PER_S)


def ros_time(stamp_ns: int) -> dict:
    """Integer nanoseconds -> a `builtin_interfaces/Time` as the dict `mcap_ros2` encodes."""
    sec, nanosec = split_ns(stamp_ns)
    return {"sec": sec, "nanosec": nanosec}


def decimal_seconds_to_ns(text: str) -> int:
    """A time written in seconds ('1.036712e-01', '1700000000.123456789') -> the nearest
    integer nanosecond, from the decimal text itself: a float would shift epoch stamps by up
    to 128 ns. ValueError naming the text when it is not a finite number."""
    try:
        value = Decimal(text.strip())
    except InvalidOperation:
        raise ValueError(f"{text.strip()[:40]!r} is not a number of seconds") from None
    if not value.is_finite():
        raise ValueError(f"{text.strip()[:40]!r} is not a finite number of seconds")
    return int((value * NS_PER_S).to_integral_value())


def parse_start_time_ns(text: str) -> int:
    """A start time from the command line -> integer nanoseconds since the epoch.

    Decimal or exponent notation is seconds ('1700000000.5'); a whole number is seconds below
    10^12 and nanoseconds from there on ('1700000000500000000'). ValueError when it is no
    time, or negative."""
    text = text.strip()
    if text.isdigit() and int(text) >= NS_THRESHOLD:
        ns = int(text)
    else:
        ns = decimal_seconds_to_ns(text)
    if not 0 <= ns < 2**63:
        raise ValueError(f"start time {text[:40]!r} is not between the epoch and 2262")
    return ns


def seconds_to_ns(stamp_s: float) -> int:
    """Float seconds (a `Scan.stamp_s`) -> the nearest integer nanosecond."""
    return int(round(stamp_s * 1e9))


def scan_stamp_ns(scan: Any) -> int:
    """A `Scan`'s stamp in integer nanoseconds: exactly the header stamp when it was read from
    a recording (its `source.stamp_ns`), else the nearest nanosecond of `stamp_s`."""
    stamp_ns = getattr(scan.source, "stamp_ns", None)
    return int(stamp_ns) if stamp_ns is not None else seconds_to_ns(scan.stamp_s)


def map_stamp_ns(snapshot: Any, first_scan: Any | None) -> int:
    """When a map is published: at the first scan's stamp (so playback shows it from the
    start), else at the last voxel update (`snapshot.t_last`, seconds); never before 0."""
    if first_scan is not None:
        return max(scan_stamp_ns(first_scan), 0)
    return max(seconds_to_ns(float(snapshot.t_last.max())), 0) if len(snapshot) else 0
