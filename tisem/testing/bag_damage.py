"""Damaged bags that `tisem.io.bag_open` reads: small intact ones, and seeded byte edits of them.

The intact bags hold the synthetic recording of `tisem.synth.mcap_log` written again by
`rosbags`: as ROS 1 (noetic types) in small chunks, bz2, lz4 or uncompressed, and as the `.db3`
of a rosbag2 folder; and a longer recording as a second `.db3` (`db3-long`: larger clouds, whose
data runs over pages of its own, and /tf at a high rate, so that the messages table takes many
leaf pages under an interior root, as a real recording's does). An edit is a cut, bit flips, a
run of bytes overwritten or inserted (at a record's or page's start, or anywhere), or a ROS 1
bag header's index position zeroed (a recording that did not close), with or without a cut.
Neither format checksums its data: a change inside the message data of an uncompressed or lz4
chunk, or anywhere in a `.db3`, can give other values that are still valid, which no reader can
notice (`detectable` False); bz2 checks each of its blocks.
"""

from __future__ import annotations

import dataclasses
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tisem.io.ros1_linear import OP_BAG_HEADER, OP_CHUNK, OP_CHUNK_INFO, OP_INDEX_DATA
from tisem.synth.mcap_log import write_synthetic_log
from tisem.testing.mcap_damage import Mutation  # (a byte edit: what, of which base, its bytes)

BASES = ("bz2", "lz4", "uncompressed", "db3", "db3-long")
PAGE = 4096  # a .db3's page size (rosbags' writer keeps SQLite's default)
_COMMON = dict(n_scans=5, n_points=40, tf_rate_hz=20.0, seed=7)
# the longer .db3: clouds of ~25 kB (a chain of overflow pages each), /tf at 250 Hz
_LONG = dict(n_scans=8, n_points=1200, tf_rate_hz=250.0, seed=8)
CHUNK_BYTES = 1500  # (a chunk or two per cloud)


def recorded_messages(mcap_path: Path) -> list[tuple[str, str, int, bytes]]:
    """(topic, type, log time ns, CDR bytes) of each message of a ROS 2 MCAP recording."""
    from mcap.reader import make_reader

    with open(mcap_path, "rb") as f:
        return [
            (channel.topic, schema.name, message.log_time, bytes(message.data))
            for schema, channel, message in make_reader(f).iter_messages()
        ]


def write_ros1_bag(
    path: Path,
    messages,
    compression: str | None = None,
    chunk_bytes: int | None = None,
    old_tf: bool = False,
) -> Path:
    """ROS 2 messages (`recorded_messages`) as a ROS 1 bag of noetic types (ROS 1 headers carry
    a `seq`; noetic has no tf2), chunks compressed with `compression` ("BZ2", "LZ4" or None)
    and closed after `chunk_bytes`; with `old_tf`, transforms as `tf/tfMessage` (tf before
    tf2, in bags of older ROS 1 releases) instead of `tf2_msgs/TFMessage`."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    humble = get_typestore(Stores.ROS2_HUMBLE)
    noetic = get_typestore(Stores.ROS1_NOETIC)
    for name in ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage"):
        noetic.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", name))

    def to_ros1(obj):
        if dataclasses.is_dataclass(obj):
            cls = noetic.types[obj.__msgtype__]
            return cls(
                **{
                    f.name: to_ros1(getattr(obj, f.name)) if hasattr(obj, f.name) else 0
                    for f in dataclasses.fields(cls)
                }
            )
        return [to_ros1(x) for x in obj] if isinstance(obj, list) else obj

    writer = Writer(path)
    if compression is not None:
        writer.set_compression(getattr(Writer.CompressionFormat, compression))
    if chunk_bytes is not None:
        writer.chunk_threshold = chunk_bytes
    with writer:
        connections = {}
        for topic, msgtype, t, data in messages:
            ros1_type = "tf/msg/tfMessage" if old_tf and msgtype.startswith("tf2_") else msgtype
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, ros1_type, typestore=noetic)
            msg = to_ros1(humble.deserialize_cdr(data, msgtype))
            writer.write(connections[topic], t, noetic.serialize_ros1(msg, ros1_type))
    return path


def write_db3(folder: Path, messages) -> Path:
    """ROS 2 messages (`recorded_messages`) as the one `.db3` file of a rosbag2 folder."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    humble = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(folder, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        connections = {}
        for topic, msgtype, t, data in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=humble)
            writer.write(connections[topic], t, data)
    return next(folder.glob("*.db3"))


@dataclass
class Base:
    name: str
    path: Path
    data: bytes
    records: list[tuple[int, int, int, int]]  # (start, data start, end, op): top-level records

    def checked(self, at: int) -> bool:
        """Whether a change of byte `at` can be noticed: in the header of a record other than
        the index's (its framing; `rosbags` trusts the index, whose counts and positions, once
        changed, can drop a message unseen), in the bag header's padding (it changes nothing),
        in a bz2 chunk's data. SQLite checks no page: a `.db3` byte, never."""
        if is_db3(self.name):
            return False
        for head, start, end, op in self.records:
            if head <= at < end:
                if op in (OP_INDEX_DATA, OP_CHUNK_INFO):
                    return False
                return at < start or op == OP_BAG_HEADER or (op == OP_CHUNK and self.name == "bz2")
        return True  # (the magic)


def _top_records(data: bytes) -> list[tuple[int, int, int, int]]:
    from tisem.io.ros1_linear import MAGIC, _framed, _op

    out, at = [], len(MAGIC)
    while at < len(data):
        fields, start, end = _framed(data, at, len(data), "")
        out.append((at, start, end, _op(fields)))
        at = end
    return out


def write_bases(folder: Path) -> dict[str, Base]:
    """The intact bags, written into `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    write_synthetic_log(folder / "source.mcap", **_COMMON)
    messages = recorded_messages(folder / "source.mcap")
    out = {}
    for name in BASES:
        if is_db3(name):  # (its "records": its pages)
            source = messages
            if name == "db3-long":
                write_synthetic_log(folder / "long.mcap", **_LONG)
                source = recorded_messages(folder / "long.mcap")
            path = write_db3(folder / f"{name.replace('-', '_')}_bag", source)
            data = path.read_bytes()
            out[name] = Base(
                name, path, data, [(a, a, a + PAGE, 0) for a in range(0, len(data), PAGE)]
            )
            continue
        compression = None if name == "uncompressed" else name.upper()
        path = write_ros1_bag(folder / f"{name}.bag", messages, compression, CHUNK_BYTES)
        data = path.read_bytes()
        out[name] = Base(name, path, data, _top_records(data))
    return out


def _place(base: Base, rng: np.random.Generator) -> tuple[int, str]:
    """(byte, where in words): a record's start half of the time, else anywhere."""
    if rng.random() < 0.5:
        at = base.records[int(rng.integers(len(base.records)))][0]
        return at, f"the record at byte {at}"
    at = int(rng.integers(len(base.data)))
    return at, f"byte {at}"


def _cut(base: Base, rng) -> Mutation:
    at = int(rng.integers(1, len(base.data)))
    return Mutation(base.name, f"cut at byte {at} of {len(base.data)}", True, base.data[:at])


def _flip(base: Base, rng) -> Mutation:
    data = bytearray(base.data)
    bits = [int(b) for b in rng.integers(8 * len(data), size=int(rng.integers(1, 9)))]
    for b in bits:
        data[b // 8] ^= 1 << (b % 8)
    places = sorted(b // 8 for b in bits)
    checked = all(base.checked(p) for p in places)
    return Mutation(base.name, f"bits flipped at bytes {places}", checked, bytes(data))


def _overwrite(base: Base, rng) -> Mutation:
    at, where = _place(base, rng)
    n = int(rng.integers(1, 200))
    run = bytes(n) if rng.random() < 0.5 else rng.integers(256, size=n, dtype=np.uint8).tobytes()
    data = base.data[:at] + run[: len(base.data) - at] + base.data[at + n :]
    kind = "zeros" if not any(run) else "random bytes"
    checked = all(base.checked(p) for p in range(at, min(at + n, len(base.data))))
    return Mutation(base.name, f"{n} {kind} over {where}", checked, data)


def _insert(base: Base, rng) -> Mutation:
    at, where = _place(base, rng)
    n = int(rng.integers(1, 64))
    junk = rng.integers(256, size=n, dtype=np.uint8).tobytes()
    data = base.data[:at] + junk + base.data[at:]
    return Mutation(base.name, f"{n} bytes inserted before {where}", True, data)


def _no_index(base: Base, rng) -> Mutation:
    data = bytearray(base.data)
    at = data.index(b"index_pos=") + len(b"index_pos=")
    struct.pack_into("<Q", data, at, 0)
    if rng.random() < 0.5:
        return Mutation(base.name, "index position zeroed", True, bytes(data))
    cut = int(rng.integers(at + 8, len(data)))
    # cut between two records, a bag that did not close is a shorter one: nothing can tell
    between = any(cut == start for start, _, _, _ in base.records)
    what = f"index position zeroed, cut at byte {cut}"
    return Mutation(base.name, what, not between, bytes(data[:cut]))


BYTE_EDITS = (_cut, _flip, _overwrite, _insert, _no_index)


def bag_mutation(bases: dict[str, Base], rng: np.random.Generator, kind: int) -> Mutation:
    """Mutation number `kind` (cycling over the edits) of a base `rng` picks (a `.db3` has no
    index position: a cut instead)."""
    name = BASES[int(rng.integers(len(BASES)))]
    edit = BYTE_EDITS[kind % len(BYTE_EDITS)]
    return (_cut if edit is _no_index and is_db3(name) else edit)(bases[name], rng)


def is_db3(name: str) -> bool:
    """Whether base `name` is a `.db3` (the others are ROS 1 bags)."""
    return name.startswith("db3")
