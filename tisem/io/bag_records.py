"""Record streams for `McapScanReader` from inputs other than one MCAP file.

`McapScanReader` walks a stream of Schema, Channel and message records (`records(report)`,
`excess`, `data_crc`) and decodes messages through a `decode(channel, schema, data)` object.
Two more sources give it that stream, so every bag yields the same `Scan`s through the same
survey, topic choice, tf buffer and cloud decoding (`tisem.io.mcap_messages`):

- `SplitMcapRecords`: the `.mcap` files of a rosbag2 folder, in order, each read by tisem's
  damage-tolerant `McapRecords`; schema and channel ids are renumbered across the files (every
  split file numbers its own), a bag compressed message by message has each message inflated
  (one that does not inflate is one lost message), and what was lost is reported per file;
- `RosbagRecords`: a bag that the `rosbags` library reads (rosbag2 sqlite3 storage, per-file
  compression, ROS 1 `.bag`). rosbags raises on damage rather than recovering: a bag it cannot
  open is refused with its reason, and one damaged part-way gives the messages before the
  damage, the rest reported lost.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import zstandard
from mcap.records import Channel, Schema

from tisem.errors import DatasetError
from tisem.io.mcap_items import Unvouched, unknown_loss
from tisem.io.mcap_records import LostMessages, McapMessage, McapRecords, ReadReport
from tisem.io.mcap_report import Loss


def repair_hint(storage: str) -> str:
    """How a user mends a bag that rosbags cannot read (a lost index, an old format), by what
    rosbags reads it as (`BagInput.storage`: ros1, sqlite3, mcap)."""
    if storage == "ros1":
        return (
            "reindex it (`rosbag reindex IN`) or convert it to ROS 2 (`rosbags-convert "
            "--src IN --dst OUT`)"
        )
    return (
        "rebuild its metadata (`ros2 bag reindex DIR`) or convert it (`ros2 bag convert "
        "-i IN -o out.yaml`)"
    )


ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
# larger than any message a sensor records: a frame that declares or inflates to more is damage
MAX_MESSAGE_BYTES = 1 << 30
_PIECE = 1 << 20


def inflate_message(data: bytes) -> bytes:
    """A message compressed on its own (rosbag2's per-message zstd); `zstandard.ZstdError`
    when its bytes are no frame, a damaged or cut one, or one larger than MAX_MESSAGE_BYTES."""
    size = zstandard.frame_content_size(data)  # -1: not declared
    if size > MAX_MESSAGE_BYTES:
        raise zstandard.ZstdError(f"its frame declares {size} bytes")
    if size >= 0:
        return zstandard.ZstdDecompressor().decompress(data)
    dobj = zstandard.ZstdDecompressor().decompressobj()
    out = bytearray()
    for at in range(0, len(data), _PIECE):
        out += dobj.decompress(data[at : at + _PIECE])
        if len(out) > MAX_MESSAGE_BYTES:
            raise zstandard.ZstdError(f"it inflates to more than {MAX_MESSAGE_BYTES} bytes")
    if not dobj.eof:
        raise zstandard.ZstdError("the frame is cut short")
    return bytes(out)


class SplitMcapRecords:
    """The records of several MCAP files read one after the other as one recording;
    `zstd_messages`: each message's data is a zstd frame of its own (rosbag2's per-message
    compression), inflated here; None (a folder without its metadata): each cdr message whose
    bytes begin as a zstd frame does (a CDR header never does)."""

    def __init__(self, paths: list[Path], zstd_messages: bool | None = False) -> None:
        self.paths = [Path(p) for p in paths]
        self.zstd_messages = zstd_messages
        self.parts = [McapRecords(p) for p in self.paths]
        self.excess: Counter = Counter()
        self.data_crc: str | None = None

    def records(
        self, report: ReadReport
    ) -> Iterator[Schema | Channel | McapMessage | LostMessages]:
        schema_ids: dict[tuple, int] = {}  # (name, encoding, text) -> recording id
        channel_ids: dict[tuple, int] = {}  # (topic, encoding, schema id) -> recording id
        for path, part in zip(self.paths, self.parts):
            # each file is checked against its own summary: counts must not mix across files
            own = ReadReport(path=str(path))
            local_schemas: dict[int, int] = {}
            schemas_here: dict[int, Schema] = {}  # (by the file's own ids)
            local_channels: dict[int, int] = {}
            topics: dict[int, str] = {}  # local channel id -> topic
            cdr: set[int] = set()  # local ids of cdr channels
            for rec in part.records(own):
                if isinstance(rec, Schema):
                    schemas_here[rec.id] = rec
                    key = (rec.name, rec.encoding, bytes(rec.data))
                    new = key not in schema_ids
                    local_schemas[rec.id] = schema_ids.setdefault(key, len(schema_ids) + 1)
                    if new:
                        yield dataclasses.replace(rec, id=local_schemas[rec.id])
                elif isinstance(rec, Channel):
                    schema_id = local_schemas.get(rec.schema_id, 0)
                    key = (rec.topic, rec.message_encoding, schema_id)
                    new = key not in channel_ids
                    local_channels[rec.id] = channel_ids.setdefault(key, len(channel_ids) + 1)
                    topics[rec.id] = rec.topic
                    if rec.message_encoding == "cdr":
                        cdr.add(rec.id)
                    if new:
                        yield dataclasses.replace(
                            rec, id=local_channels[rec.id], schema_id=schema_id
                        )
                elif isinstance(rec, McapMessage):
                    if rec.channel_id not in local_channels:
                        continue
                    channel = local_channels[rec.channel_id]
                    if not self._compressed(rec.data, rec.channel_id in cdr):
                        yield dataclasses.replace(rec, channel_id=channel)
                        continue
                    try:
                        yield dataclasses.replace(
                            rec, channel_id=channel, data=inflate_message(rec.data)
                        )
                    except zstandard.ZstdError as exc:
                        where = f"message at log time {rec.log_time * 1e-9:.3f} s"
                        lost = _lost_message(
                            own, topics[rec.channel_id], channel, where, exc, not rec.crc_checked
                        )
                        yield dataclasses.replace(lost, where=f"{path.name}: {where}")
                elif isinstance(rec, Unvouched):  # (its schema resolved by the file's own ids)
                    message = rec.message
                    if self._compressed(message.data, rec.channel.message_encoding == "cdr"):
                        try:
                            message = dataclasses.replace(
                                message, data=inflate_message(message.data)
                            )
                        except zstandard.ZstdError:  # (salvage only: the mount stays unread)
                            continue
                    yield dataclasses.replace(
                        rec,
                        schema=rec.schema or schemas_here.get(rec.channel.schema_id),
                        message=message,
                        where=f"{path.name}: {rec.where}",
                    )
                else:
                    # an id this file's records do not name stays one no channel has
                    channel = (
                        None
                        if rec.channel_id is None
                        else local_channels.get(rec.channel_id, -1 - rec.channel_id)
                    )
                    yield dataclasses.replace(
                        rec, channel_id=channel, where=f"{path.name}: {rec.where}"
                    )
            _merge_report(report, own, path.name)
        self.excess = sum((p.excess for p in self.parts), Counter())
        crcs = {p.data_crc for p in self.parts}
        self.data_crc = "mismatch" if "mismatch" in crcs else "match" if crcs == {"match"} else None

    def _compressed(self, data: bytes, cdr: bool) -> bool:
        """Whether a message's data is a zstd frame of its own to inflate."""
        if self.zstd_messages is None:  # (no metadata: a cdr message tells by its first bytes)
            return cdr and data[:4] == ZSTD_MAGIC
        return self.zstd_messages


def _lost_message(
    report: ReadReport, topic: str, channel: int, where: str, exc: Exception, guessed: bool
) -> LostMessages:
    """A message read whole whose compressed data does not inflate: one lost message on its
    topic (no longer counted as read). `guessed`: no CRC covers the record, so the damage that
    spoilt its data may have changed its channel id too, and the scans after it may be
    numbered otherwise than in the intact file (the reader marks them)."""
    report.messages[topic] -= 1
    report.losses.append(
        Loss(
            where,
            f"its zstd frame does not inflate ({exc})"
            + (
                "; no CRC covers its record, so the damage may have changed its channel"
                if guessed
                else ""
            ),
            messages=1,
            topics=Counter({topic: 1}),
        )
    )
    return LostMessages(channel, 1, where, guessed=guessed)


def _merge_report(into: ReadReport, part: ReadReport, name: str) -> None:
    into.messages.update(part.messages)
    into.losses += [
        dataclasses.replace(loss, where=f"{name}: {loss.where}") for loss in part.losses
    ]
    into.notes += [f"{name}: {note}" for note in part.notes]
    into.partial_chunk_messages += part.partial_chunk_messages


class RosbagRecords:
    """The messages of a bag read by `rosbags.highlevel.AnyReader`, as MCAP-like records.

    Each pass opens the bag again (a per-file compressed bag is inflated to a temporary folder
    each time). Message definitions come from the bag; a Humble `.db3` stores none, so the
    Humble type store stands in. `decoders` decodes with the bag's own type store.
    """

    def __init__(self, path: str | Path, what: str, storage: str = "") -> None:
        self.path = Path(path)
        self.what = what  # e.g. "rosbag2 folder (sqlite3)"
        self.storage = storage  # ros1 | sqlite3 | mcap: which repair to suggest
        self.excess: Counter = Counter()
        self.data_crc: str | None = None
        self.stopped = False  # whether a pass met damage it could not read past
        # (ROS 1) what the bag's index lists per topic, and where a pass yielded fewer: rosbags
        # can pass over a chunk whose header is damaged without a word
        self._indexed: Counter | None = None
        self.short: str | None = None
        with self._open() as reader:
            self._ros1 = not reader.is2
            self.typestore = reader.typestore  # kept: closing the reader only drops its name
            self.topics = {c.topic: c.msgtype for c in reader.connections}
        self.decoders = RosbagDecoders(self.typestore, self._ros1, self.path)
        if self._ros1:
            from tisem.io.ros1_linear import indexed_topic_counts

            self._indexed = indexed_topic_counts(self.path)

    def _open(self) -> Any:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        try:
            reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises many kinds on bad bags
            raise DatasetError(
                f"{self.path}: cannot read this {self.what} "
                f"({_reason(exc)}); {repair_hint(self.storage)}"
            ) from None
        return _Closing(reader)

    def records(self, report: ReadReport) -> Iterator[Schema | Channel | McapMessage]:
        if self.storage == "sqlite3":  # (sqlite checks no page: a short one reads as zeros)
            from tisem.io.db3_rows import short_page_loss

            db3s = [self.path] if self.path.is_file() else split_files(self.path, ".db3")
            for db3 in db3s:
                yield from short_page_loss(db3, report, len(db3s) > 1)
        with self._open() as reader:
            encoding = "ros1msg" if self._ros1 else "ros2msg"
            schemas: dict[str, int] = {}
            for conn in reader.connections:
                if conn.msgtype not in schemas:
                    schemas[conn.msgtype] = len(schemas) + 1
                    yield Schema(
                        id=schemas[conn.msgtype],
                        name=conn.msgtype,
                        encoding=encoding,
                        data=conn.msgdef.data.encode(),
                    )
                yield Channel(
                    id=conn.id,
                    topic=conn.topic,
                    schema_id=schemas[conn.msgtype],
                    message_encoding="ros1" if self._ros1 else "cdr",
                    metadata={},
                )
            if self.short is not None:  # (known from an earlier pass: where is unknown)
                yield LostMessages(None, None, self.short)
            read: Counter = Counter()
            try:
                for conn, stamp_ns, data in reader.messages():
                    report.messages[conn.topic] += 1
                    read[conn.topic] += 1
                    yield McapMessage(
                        channel_id=conn.id, log_time=int(stamp_ns), data=data, crc_checked=True
                    )
            except Exception as exc:  # noqa: BLE001 - a damaged storage file, mid-way
                # what was read is kept; how much the rest held is unknown
                self.stopped = True
                yield unknown_loss(
                    report,
                    f"{self.path.name} after {sum(report.messages.values())} message(s)",
                    f"the rest of the {self.what} is unreadable ({_reason(exc)}); "
                    f"{repair_hint(self.storage)}",
                )
                return
            yield from self._shortfall(read, report)

    def _shortfall(self, read: Counter, report: ReadReport) -> Iterator[LostMessages]:
        """A loss where a pass read fewer messages of a topic than the bag's index lists."""
        if self._indexed is None or self.short is not None:
            return
        from rosbags.rosbag1.reader import normalize  # (how rosbags names a bag's topics)

        indexed = Counter()
        for topic, n in self._indexed.items():
            indexed[normalize(topic)] += n
        short = {t: n - read[t] for t, n in sorted(indexed.items()) if read[t] < n}
        if not short:
            return
        self.stopped = True  # (so that the bag is also read record by record)
        self.short = f"{self.path.name} (somewhere: its index lists messages rosbags did not give)"
        report.losses.append(
            Loss(
                self.path.name,
                "rosbags yielded fewer messages than the bag's index lists ("
                + ", ".join(f"{n} on {t}" for t, n in short.items())
                + "): a damaged chunk it passed over? where they were is unknown",
                uncounted=True,
            )
        )
        yield LostMessages(None, None, self.short)


class _Closing:
    """`with` for an already opened AnyReader (opening is where rosbags reports bad bags)."""

    def __init__(self, reader: Any) -> None:
        self.reader = reader

    def __enter__(self) -> Any:
        return self.reader

    def __exit__(self, *exc: object) -> None:
        self.reader.close()


class RosbagDecoders:
    """`decode(channel, schema, data)` with a bag's `rosbags` type store (CDR or ROS 1)."""

    def __init__(self, typestore: Any, ros1: bool, path: Path) -> None:
        self._deserialize = typestore.deserialize_ros1 if ros1 else typestore.deserialize_cdr
        self.path = path

    def decode(self, channel: Channel, schema: Schema | None, data: bytes) -> Any:
        if schema is None:
            raise DatasetError(f"{self.path}: topic {channel.topic} has no message type")
        return self._deserialize(data, schema.name)


def _reason(exc: Exception) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {text[:200]}" if text else type(exc).__name__


def split_files(folder: Path, suffix: str) -> list[Path]:
    """The folder's files with this suffix, in split order."""
    return sorted((p for p in folder.glob(f"*{suffix}") if p.is_file()), key=_split_order)


def _split_order(path: Path) -> tuple:
    """rosbag2 names its splits NAME_0, NAME_1, ... NAME_10: order them by that number."""
    stem = path.stem
    digits = len(stem) - len(stem.rstrip("0123456789"))
    return (stem[: len(stem) - digits], int(stem[len(stem) - digits :] or -1), path.name)
