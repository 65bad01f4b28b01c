"""Labelled LiDAR scans from an MCAP recording, damaged or not.

Two layers:

1. Records. The stock `mcap` reader returns nothing for a truncated file (the footer read fails
   first) and returns corrupted bytes silently unless asked to check CRCs, and then stops at
   the first bad chunk (notes/mcap-lidar-logs.md §3). So records are read here: through the
   chunk index when the summary is intact (a chunk whose own header is damaged cannot derail
   the others), linearly otherwise. Each chunk is decompressed and CRC-checked on its own; a
   bad one is skipped and its loss counted from the message index records, a file cut short
   gives every message that was completely written (also from the partial last chunk, whose
   prefix is intact), and everything lost goes into a `ReadReport`.

2. Scans. `McapScanReader` reads the file twice: a survey pass decodes only pose messages
   (/tf, /tf_static, `--pose-topic`), counts messages, picks the cloud topic and checks the
   first cloud's fields and frame, so every "this cannot work" error comes before any mapping;
   the second pass decodes clouds one at a time and yields `Scan`s with the pose looked up at
   the header stamp from the full transform buffer (exactly what tf2 gives offline). A scan
   that cannot be used becomes a `SkippedScan` with the reason.
"""
from __future__ import annotations

import io
import itertools
import logging
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import lz4.frame
import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema

from tisem.errors import DatasetError, ScanError, SkippedScan
from tisem.io import pointcloud2 as pc2
from tisem.io.tf import POSE_SCHEMAS, TF_SCHEMAS, TfBuffer, TfError, make_transform, pose_edges
from tisem.labels import NUM_CLASSES, raw_to_train
from tisem.scan import McapSource, Scan

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
CLOUD_SCHEMAS = ("sensor_msgs/msg/PointCloud2", "foxglove.PointCloud")
# point-cloud-like schemas we recognise but cannot map, to say so instead of "no cloud topic"
UNSUPPORTED_CLOUDS = ("sensor_msgs/PointCloud2", "foxglove.CompressedPointCloud",
                      "sensor_msgs/msg/LaserScan", "foxglove.LaserScan")


# ---- what was lost ---------------------------------------------------------------------------

@dataclass
class Loss:
    """One piece of the file that could not be used."""

    where: str                      # e.g. "chunk at byte 1234 (log time 1.0-1.2 s)"
    what: str                       # why it was lost
    messages: int | None = None     # how many messages it held, None when unknowable
    topics: Counter = field(default_factory=Counter)

    def line(self) -> str:
        held = ("" if self.messages is None else
                f": {self.messages} message(s) lost" +
                (f" ({', '.join(f'{n} on {t}' for t, n in sorted(self.topics.items()))})"
                 if self.topics else ""))
        return f"{self.where}: {self.what}{held}"


@dataclass
class ReadReport:
    """Everything the reader could not use, and why. Empty `losses` = the file was whole."""

    path: str = ""
    losses: list[Loss] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    messages: Counter = field(default_factory=Counter)       # topic -> messages recovered
    skipped: list[SkippedScan] = field(default_factory=list)
    unknown_labels: int = 0          # points whose label id is unknown (-> 0)
    unknown_gt_labels: int = 0
    partial_chunk_messages: int = 0  # recovered from a chunk the file ends inside

    def lines(self) -> list[str]:
        out = [loss.line() for loss in self.losses] + list(self.notes)
        if self.partial_chunk_messages:
            out.append(f"{self.partial_chunk_messages} message(s) recovered from the incomplete "
                       f"last chunk (its CRC cannot be checked; cut files keep their bytes)")
        out += [f"skipped scan {s.index} ({s.name}): {s.reason}" for s in self.skipped]
        if self.unknown_labels:
            out.append(f"{self.unknown_labels} point(s) with an unknown label id mapped to 0")
        if self.unknown_gt_labels:
            out.append(f"{self.unknown_gt_labels} point(s) with an unknown ground-truth id -> 0")
        return out

    def to_dict(self) -> dict:
        return {"path": self.path, "damaged": bool(self.losses),
                "losses": [loss.line() for loss in self.losses], "notes": list(self.notes),
                "messages": dict(self.messages),
                "skipped_scans": [{"index": s.index, "name": s.name, "reason": s.reason}
                                  for s in self.skipped],
                "unknown_labels": self.unknown_labels,
                "unknown_gt_labels": self.unknown_gt_labels,
                "partial_chunk_messages": self.partial_chunk_messages}


# ---- layer 1: records ------------------------------------------------------------------------

class _BadChunk(Exception):
    pass


@dataclass
class LostMessages:
    """Yielded where a skipped chunk held `count` messages of a channel (from its message
    index), so that readers can keep numbering messages as in the intact file."""

    channel_id: int
    count: int
    where: str


def _message(buf) -> Message:
    channel_id, sequence, log_time, publish_time = struct.unpack_from("<HIQQ", buf, 0)
    return Message(channel_id=channel_id, sequence=sequence, log_time=log_time,
                   publish_time=publish_time, data=bytes(buf[22:]))


def _record(opcode: int, buf):
    """Schema, Channel or Message from a record's content; None for every other record."""
    if opcode == Opcode.MESSAGE:
        return _message(buf)
    if opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
        stream = ReadDataStream(io.BytesIO(bytes(buf)))
        return Schema.read(stream) if opcode == Opcode.SCHEMA else Channel.read(stream)
    return None


def _chunk_fields(buf):
    """(start, end, uncompressed size, crc, compression, data) of a chunk record's content.
    `data` may be shorter than declared when the file ends inside the chunk."""
    start, end, size, crc, clen = struct.unpack_from("<QQQII", buf, 0)
    compression = bytes(buf[32:32 + clen]).decode()
    (dlen,) = struct.unpack_from("<Q", buf, 32 + clen)
    data = memoryview(buf)[40 + clen:40 + clen + dlen]          # a view: chunks are big
    return start, end, size, crc, compression, data, dlen


def _inflate(compression: str, data, size: int, complete: bool):
    if compression == "":
        return data
    if compression == "zstd":
        if complete:
            return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        return zstandard.ZstdDecompressor().decompressobj().decompress(bytes(data))
    if compression == "lz4":
        if complete:
            return lz4.frame.decompress(data)       # takes the buffer: no copy of the input
        return lz4.frame.LZ4FrameDecompressor().decompress(bytes(data))
    raise _BadChunk(f"unsupported compression {compression!r}")


def _inner_records(data: bytes, complete: bool) -> list:
    """Records inside a decompressed chunk. In a complete chunk a record that overruns it means
    corruption (the whole chunk is rejected); in a partial one it is where the cut was."""
    out, pos, view = [], 0, memoryview(data)
    while pos < len(data):
        if pos + 9 > len(data):
            break
        opcode, length = struct.unpack_from("<BQ", data, pos)
        end = pos + 9 + length
        if end > len(data):
            break
        rec = _record(opcode, view[pos + 9:end])
        if rec is not None:
            out.append(rec)
        pos = end
    if complete and pos != len(data):
        raise _BadChunk("its records do not fill it exactly")
    return out


def _read_at(f, pos: int, n: int) -> bytes:
    f.seek(pos)
    return f.read(n)


def _time_range(start: int, end: int) -> str:
    return f"log time {start / 1e9:.3f}-{end / 1e9:.3f} s"


# the records the linear reader needs the content of (others are skipped unread)
_DATA_OPCODES = (Opcode.CHUNK, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE)

# untrusted bytes: any of these from a decompressor or parser means "this chunk is bad"
_CHUNK_ERRORS = (_BadChunk, zstandard.ZstdError, RuntimeError, struct.error, ValueError,
                 UnicodeDecodeError, McapError, EOFError)


class McapRecords:
    """Schema, Channel and Message records of an MCAP file, in file order, surviving damage."""

    def __init__(self, path):
        self.path = str(path)
        try:
            self.size = Path(path).stat().st_size
        except OSError as e:
            raise DatasetError(f"{path}: cannot open ({e.strerror})") from None
        if self.size == 0:
            raise DatasetError(f"{path}: the file is empty")
        with open(path, "rb") as f:
            if f.read(8) != MAGIC:
                raise DatasetError(f"{path}: not an MCAP file (it does not start with the MCAP "
                                   f"magic bytes)")
            try:  # the summary: schemas, channels, chunk index, message counts
                f.seek(0)
                self.summary = make_reader(f).get_summary()
            # a damaged tail raises any of these (notes §3); without a summary we read linearly
            except (McapError, ValueError, struct.error, OSError, UnicodeDecodeError):
                self.summary = None
        self._no_crc = 0

    def records(self, report: ReadReport) -> Iterator:
        """Yield Schema, Channel, Message and LostMessages records; count messages per topic
        and append what was dropped to `report`."""
        channels: dict[int, Channel] = {}
        orphans = Counter()
        self._no_crc = 0
        with open(self.path, "rb") as f:
            if self.summary is not None:
                # the summary repeats schemas and channels: they survive a lost chunk
                source = [*self.summary.schemas.values(), *self.summary.channels.values()]
                if self.summary.chunk_indexes:
                    source = itertools.chain(source, self._indexed(f, report))
                else:
                    report.notes.append("no chunk index: the file was read linearly")
                    source = itertools.chain(source, self._linear(f, report))
            else:
                report.notes.append("no summary section (cut short, or written without one): "
                                    "the file was read linearly")
                source = self._linear(f, report)
            for rec in source:
                if isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is None:                    # its Channel record was in a lost chunk
                        orphans[rec.channel_id] += 1
                        continue
                    report.messages[ch.topic] += 1
                yield rec
        if self._no_crc:
            report.notes.append(f"{self._no_crc} chunk(s) carry no CRC (rosbag2's default): "
                                f"corrupted bytes inside them cannot be detected")
        for cid, n in orphans.items():
            report.losses.append(Loss(f"channel {cid}", "its Channel record was lost, so its "
                                      "messages cannot be decoded", messages=n,
                                      topics=Counter({f"channel {cid}": n})))
        self._check_counts(report)

    # -- chunks
    def _chunk(self, buf, complete: bool = True) -> list:
        _, _, size, crc, compression, data, _ = _chunk_fields(buf)
        data = _inflate(compression, data, size, complete)
        if complete:
            if len(data) != size:
                raise _BadChunk(f"it inflates to {len(data)} bytes, not {size}")
            if crc == 0:
                self._no_crc += 1
            elif zlib.crc32(data) != crc:
                raise _BadChunk("its CRC does not match: corrupted bytes")
        return _inner_records(data, complete)

    def _safe_chunk(self, buf, where: str, report: ReadReport) -> tuple[list, Loss | None]:
        try:
            return self._chunk(buf), None
        except _CHUNK_ERRORS as e:
            why = str(e) if isinstance(e, _BadChunk) else f"{type(e).__name__}: {e}"
            loss = Loss(where, f"chunk skipped ({why})", messages=0)
            report.losses.append(loss)
            return [], loss

    def _indexed(self, f, report: ReadReport) -> Iterator:
        """Chunk by chunk through the chunk index: a chunk's damage stays in that chunk."""
        for ci in sorted(self.summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            pos = ci.chunk_start_offset
            where = f"chunk at byte {pos} ({_time_range(ci.message_start_time, ci.message_end_time)})"
            ok = 9 <= ci.chunk_length and pos + ci.chunk_length <= self.size
            if ok:
                opcode, length = struct.unpack("<BQ", _read_at(f, pos, 9))
                ok = opcode == Opcode.CHUNK and 9 + length == ci.chunk_length
            if ok:
                records, loss = self._safe_chunk(f.read(length), where, report)
                yield from records
            else:
                loss = Loss(where, "chunk skipped (its record header does not match the index)",
                            messages=0)
                report.losses.append(loss)
            if loss is not None:
                for off in ci.message_index_offsets.values():
                    lost = self._count_lost(f, off, loss, self.summary.channels)
                    if lost is not None:
                        yield lost

    def _count_lost(self, f, pos: int, loss: Loss, channels: dict) -> LostMessages | None:
        """Add the messages a MessageIndex record (at `pos`) lists to a lost chunk's count."""
        try:
            opcode, length, channel_id, nbytes = struct.unpack("<BQHI", _read_at(f, pos, 15))
        except struct.error:
            return None
        if opcode != Opcode.MESSAGE_INDEX or pos + 9 + length > self.size:
            return None
        n = nbytes // 16                                # (log_time, offset) pairs
        ch = channels.get(channel_id)
        loss.messages = (loss.messages or 0) + n
        loss.topics[ch.topic if ch else f"channel {channel_id}"] += n
        return LostMessages(channel_id, n, loss.where) if n else None

    def _linear(self, f, report: ReadReport) -> Iterator:
        """Record after record from the start; stops where the file is cut or unparseable."""
        pos, size = 8, self.size
        last_loss: Loss | None = None           # the MessageIndex records after a bad chunk
        channels: dict[int, Channel] = dict(self.summary.channels) if self.summary else {}
        while True:
            if pos == size:
                report.losses.append(Loss(f"end of file (byte {size})", "no data-end record or "
                                          "footer: the recording was cut short at a record "
                                          "boundary; what followed is unknown"))
                return
            if pos + 9 > size:
                report.losses.append(Loss(f"byte {pos}", f"the file ends inside a record header "
                                          f"({size - pos} of 9 bytes): cut short"))
                return
            opcode, length = struct.unpack("<BQ", _read_at(f, pos, 9))
            end = pos + 9 + length
            if opcode == 0 or 0x10 < opcode < 0x80:   # 0x80-0xff are private, legal records
                report.losses.append(Loss(f"byte {pos}", f"invalid record opcode {opcode:#x}: "
                                          f"the file is corrupt from here on"))
                return
            if end > size:
                yield from self._cut_record(f, pos, opcode, length, report)
                return
            if opcode == Opcode.MESSAGE_INDEX:
                if last_loss is not None:
                    lost = self._count_lost(f, pos, last_loss, channels)
                    if lost is not None:
                        yield lost
                pos = end
                continue
            buf = f.read(length) if opcode in _DATA_OPCODES else b""
            if opcode == Opcode.CHUNK:
                where = f"chunk at byte {pos}"
                if length >= 16:
                    where += f" ({_time_range(*struct.unpack_from('<QQ', buf, 0))})"
                records, last_loss = self._safe_chunk(buf, where, report)
                for rec in records:
                    if isinstance(rec, Channel):
                        channels[rec.id] = rec
                    yield rec
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):   # unchunked files
                try:
                    rec = _record(opcode, buf)
                    if isinstance(rec, Channel):
                        channels[rec.id] = rec
                    yield rec
                except _CHUNK_ERRORS as e:
                    report.losses.append(Loss(f"record at byte {pos}", f"unparseable "
                                              f"({type(e).__name__})", messages=None))
            elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                return                                  # the summary follows: data complete
            pos = end

    def _cut_record(self, f, pos: int, opcode: int, length: int, report: ReadReport):
        """The file ends inside a record: say so, and yield what a cut chunk still holds."""
        have = self.size - pos - 9
        try:
            name = Opcode(opcode).name.lower().replace("_", " ")
        except ValueError:
            name = f"opcode {opcode:#x}"
        loss = Loss(f"byte {pos}", f"the file ends inside a {name} record ({have} of {length} "
                    f"bytes present): cut short; anything after it is lost")
        report.losses.append(loss)
        if opcode != Opcode.CHUNK:
            return
        buf = _read_at(f, pos + 9, have)
        try:
            start, stop = struct.unpack_from("<QQ", buf, 0)
            loss.where = f"chunk at byte {pos} ({_time_range(start, stop)})"
            records = _inner_records(self._chunk_prefix(buf), complete=False)
        except _CHUNK_ERRORS:
            return
        report.partial_chunk_messages += sum(isinstance(r, Message) for r in records)
        yield from records

    @staticmethod
    def _chunk_prefix(buf) -> bytes:
        """What the first bytes of a cut chunk inflate to (a prefix of its records)."""
        _, _, size, _, compression, data, _ = _chunk_fields(buf)
        return _inflate(compression, data, size, complete=False)

    def _check_counts(self, report: ReadReport) -> None:
        """With a summary, compare what was read with the recorded message counts."""
        stats = self.summary.statistics if self.summary else None
        if stats is None:
            return
        missing = Counter()
        for cid, n in stats.channel_message_counts.items():
            ch = self.summary.channels.get(cid)
            topic = ch.topic if ch else f"channel {cid}"
            if report.messages[topic] < n:
                missing[topic] = n - report.messages[topic]
        accounted = Counter()
        for loss in report.losses:
            accounted.update(loss.topics)
        unaccounted = missing - accounted
        if unaccounted:
            report.losses.append(Loss("summary statistics", "messages counted in the summary "
                                      "were not found", messages=sum(unaccounted.values()),
                                      topics=unaccounted))


# ---- layer 2: scans --------------------------------------------------------------------------

@dataclass
class McapOptions:
    """How to turn a recording into scans (the `map_mcap.py` options)."""

    topic: str | None = None            # the cloud topic; found automatically when there is one
    label_field: str = "label"          # per-point label field ...
    label_space: str = "raw"            # ... holding raw SemanticKITTI ids or train ids
    prob_field: str | None = None       # or a count=C float field of class probabilities
    gt_field: str | None = None         # ground-truth label field (same label space), for metrics
    map_frame: str = "map"
    pose_topic: str | None = None       # Odometry / PoseStamped instead of /tf (dynamic)
    pose_child_frame: str | None = None # the frame a PoseStamped is the pose of (default: the
                                        # top of the cloud frame's /tf_static chain)
    tf_tolerance_s: float = 0.0         # allowed extrapolation beyond a transform's samples
    first: int = 0                      # scans by message order, last inclusive
    last: int | None = None
    num_classes: int = NUM_CLASSES

    def validate(self) -> None:
        if self.label_space not in ("raw", "train"):
            raise ValueError(f"label_space must be 'raw' or 'train', got {self.label_space!r}")
        if self.tf_tolerance_s < 0:
            raise ValueError("tf_tolerance_s must be >= 0")


class _Decoders:
    """One decode function per channel, from the ROS 2 and protobuf decoder factories."""

    def __init__(self):
        from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoders
        from mcap_ros2.decoder import DecoderFactory as Ros2Decoders
        self._factories = [Ros2Decoders(), ProtobufDecoders()]
        self._cache: dict[int, object] = {}

    def decode(self, channel: Channel, schema: Schema | None, data: bytes):
        fn = self._cache.get(channel.id)
        if fn is None:
            for factory in self._factories:
                fn = factory.decoder_for(channel.message_encoding, schema)
                if fn is not None:
                    break
            else:
                raise ScanError(f"no decoder for {channel.message_encoding!r} messages with schema "
                                f"{schema.encoding if schema else None!r} on {channel.topic}")
            self._cache[channel.id] = fn
        return fn(data)


def _stamp_ns(stamp) -> int:
    if hasattr(stamp, "nanosec"):
        return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return int(stamp.seconds) * 1_000_000_000 + int(stamp.nanos)


def _cloud_parts(schema_name: str, msg):
    """(structured points, frame_id, stamp_ns, T_frame_cloud) of a decoded cloud message."""
    if schema_name == "foxglove.PointCloud":
        p, q = msg.pose.position, msg.pose.orientation
        quat = (q.x, q.y, q.z, q.w) if any((q.x, q.y, q.z, q.w)) else (0, 0, 0, 1)  # unset pose
        return (pc2.foxglove_cloud_to_array(msg), msg.frame_id, _stamp_ns(msg.timestamp),
                make_transform((p.x, p.y, p.z), quat))
    return pc2.ros_cloud_to_array(msg), msg.header.frame_id, _stamp_ns(msg.header.stamp), None


def _describe_topics(counts: Counter, kinds: dict) -> str:
    return ", ".join(f"{t} ({kinds.get(t, '?')}, {n} msgs)" for t, n in sorted(counts.items()))


class McapScanReader:
    """Scans from an MCAP log: iterate for `Scan | SkippedScan`, in message order.

    Construction surveys the file (raises `DatasetError` with a clear message when nothing can
    be mapped: no cloud topic, an ambiguous one, a missing label field, no transform path).
    Afterwards: `topic`, `frame_id`, `total` (scans that will be yielded), `tf` (the buffer),
    `report` (damage found while surveying; skipped scans and unknown labels are added while
    iterating).
    """

    def __init__(self, path, options: McapOptions | None = None):
        self.options = options or McapOptions()
        self.options.validate()
        self.path = str(path)
        self.report = ReadReport(path=self.path)
        self._records = McapRecords(path)
        self._decoders = _Decoders()
        self._survey()

    # -- pass 1
    def _survey(self) -> None:
        opts = self.options
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        kinds: dict[str, str] = {}                    # topic -> schema name
        samples = []                                  # (static, foxglove, parent, child, t, xyz, q)
        first_cloud: dict[str, object] = {}           # topic -> first decodable cloud
        undecodable = Counter()
        lost_clouds = Counter()                       # channel id -> messages in lost chunks
        for rec in self._records.records(self.report):
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
                continue
            if isinstance(rec, Channel):
                channels[rec.id] = rec
                schema = schemas.get(rec.schema_id)
                kinds[rec.topic] = schema.name if schema else "?"
                continue
            if isinstance(rec, LostMessages):
                lost_clouds[rec.channel_id] += rec.count
                continue
            ch = channels[rec.channel_id]
            name = kinds[ch.topic]
            # with --pose-topic, /tf is ignored but /tf_static still gives the sensor mount
            static = ch.topic.endswith("tf_static")
            is_pose = (name in TF_SCHEMAS and (opts.pose_topic is None or static)
                       or ch.topic == opts.pose_topic)
            wants_cloud = (name in CLOUD_SCHEMAS and ch.topic not in first_cloud
                           and (opts.topic is None or ch.topic == opts.topic))
            if not (is_pose or wants_cloud):
                continue
            try:
                msg = self._decoders.decode(ch, schemas.get(ch.schema_id), rec.data)
                if wants_cloud:
                    first_cloud[ch.topic] = _cloud_parts(name, msg)
                    continue
                edges = pose_edges(name, msg, default_parent=opts.map_frame, default_child=None)
            # a damaged message (bad CRC-less chunk) or a schema we cannot parse: count it
            except Exception as e:  # noqa: BLE001 - decoders raise anything on bad bytes
                undecodable[ch.topic] += 1
                log.debug("undecodable message on %s: %r", ch.topic, e)
                continue
            fox = name.startswith("foxglove.")
            samples += [(static, fox, *e) for e in edges]
        for topic, n in undecodable.items():
            self.report.losses.append(Loss(topic, "messages could not be decoded", messages=n,
                                           topics=Counter({topic: n})))
        self._kinds = kinds
        self._schemas, self._channels = schemas, channels
        self.topic = self._pick_topic(kinds, first_cloud)
        self._check_first_cloud(first_cloud.get(self.topic))
        self._build_tf(samples)
        self._check_tf()
        n = self.report.messages[self.topic] + sum(
            k for cid, k in lost_clouds.items()
            if cid in channels and channels[cid].topic == self.topic)
        last = n - 1 if opts.last is None else min(opts.last, n - 1)
        self.total = max(0, last - opts.first + 1)

    def _pick_topic(self, kinds: dict, first_cloud: dict) -> str:
        counts = Counter({t: self.report.messages[t] for t in kinds})
        clouds = {t for t, k in kinds.items() if k in CLOUD_SCHEMAS and counts[t] > 0}
        where = f"{self.path}"

        def listing(topics) -> str:
            return _describe_topics(Counter({c: counts[c] for c in topics}), kinds) or "none"

        if self.options.topic is not None:
            t = self.options.topic
            if t not in kinds:
                raise DatasetError(f"{where}: no topic {t!r}; point-cloud topics: {listing(clouds)}")
            if kinds[t] not in CLOUD_SCHEMAS:
                raise DatasetError(f"{where}: topic {t!r} carries {kinds[t]}, not a point cloud "
                                   f"tisem reads ({', '.join(CLOUD_SCHEMAS)})")
            clouds = {t}
        if not clouds:
            other = [t for t, k in kinds.items() if k in UNSUPPORTED_CLOUDS]
            hint = (f"; {', '.join(f'{t} ({kinds[t]})' for t in other)} cannot be read "
                    f"(supported: {', '.join(CLOUD_SCHEMAS)})" if other else "")
            damage = ("; the file is damaged: " + "; ".join(self.report.lines())
                      if self.report.losses else "")
            raise DatasetError(f"{where}: no point-cloud messages found{hint}; topics: "
                               f"{_describe_topics(counts, kinds) or 'none'}{damage}")
        if len(clouds) > 1:
            raise DatasetError(f"{where}: several point-cloud topics, choose one with --topic: "
                               f"{listing(clouds)}")
        topic = clouds.pop()
        if topic not in first_cloud:
            raise DatasetError(f"{where}: none of the {counts[topic]} messages on {topic} "
                               f"could be decoded")
        return topic

    def _check_first_cloud(self, parts) -> None:
        """Missing fields are a property of the recording: say so before mapping anything."""
        arr, frame_id, _, _ = parts
        self.frame_id = frame_id
        opts = self.options
        needed = ["x", "y", "z", opts.prob_field or opts.label_field]
        if opts.gt_field:
            needed.append(opts.gt_field)
        missing = [f for f in needed if not pc2.has_field(arr, f)]
        if missing:
            what = {opts.label_field: "label field (--label-field)",
                    opts.prob_field: "probability field (--prob-field)",
                    opts.gt_field: "ground-truth field (--gt-field)"}
            raise DatasetError(
                f"{self.path}: the clouds on {self.topic} have no "
                f"{' and no '.join(repr(f) + ' ' + what.get(f, 'field') for f in missing)}; "
                f"their fields are: {pc2.describe_fields(arr)}")
        if not frame_id:
            raise DatasetError(f"{self.path}: the clouds on {self.topic} have an empty frame_id")

    def _build_tf(self, samples: list) -> None:
        opts = self.options
        self.tf = TfBuffer(max_extrapolation_s=opts.tf_tolerance_s)
        for static, fox, parent, child, t, xyz, q in samples:
            if static:
                self.tf.add(parent, child, t, xyz, q, static=True)
        # a PoseStamped names no child: by default it is the pose of the top of the sensor's
        # static mount (base_link for base_link -> velodyne), or of the sensor when unmounted
        child_default = opts.pose_child_frame or self.tf.root_of(self.frame_id)
        fox_children = set()
        for static, fox, parent, child, t, xyz, q in samples:
            if static:
                continue
            self.tf.add(parent, child or child_default, t, xyz, q)
            if fox:
                fox_children.add((child or child_default).lstrip("/"))
        if fox_children:
            promoted = self.tf.promote_constant_edges(fox_children)
            if promoted:
                self.report.notes.append(f"foxglove transforms that never change were taken as "
                                         f"static: {', '.join(sorted(promoted))}")
        self.report.notes += [f"tf: {w}" for w in self.tf.warnings]

    def _check_tf(self) -> None:
        opts = self.options
        if opts.pose_topic is not None and opts.pose_topic not in self._kinds:
            raise DatasetError(f"{self.path}: no topic {opts.pose_topic!r}; topics: "
                               f"{_describe_topics(self.report.messages, self._kinds)}")
        if opts.pose_topic is not None and self._kinds[opts.pose_topic] not in POSE_SCHEMAS:
            raise DatasetError(f"{self.path}: --pose-topic {opts.pose_topic} carries "
                               f"{self._kinds[opts.pose_topic]}; supported: "
                               f"{', '.join(POSE_SCHEMAS)}")
        if self.frame_id.lstrip("/") == opts.map_frame.lstrip("/"):
            return
        if not self.tf.can_connect(opts.map_frame, self.frame_id):
            try:
                self.tf.lookup(opts.map_frame, self.frame_id, 0)
            except TfError as e:
                raise DatasetError(f"{self.path}: no transform from the map frame "
                                   f"{opts.map_frame!r} to the cloud frame {self.frame_id!r} "
                                   f"(--map-frame, --pose-topic): {e}") from None

    # -- pass 2
    def __len__(self) -> int:
        return self.total

    def __iter__(self) -> Iterator[Scan | SkippedScan]:
        opts = self.options
        scratch = ReadReport()               # damage was reported by the survey already
        index = -1
        targets = set()                      # channel ids of the topic (usually one)
        for rec in self._records.records(scratch):
            if isinstance(rec, Channel):
                if rec.topic == self.topic:
                    targets.add(rec.id)
                continue
            if isinstance(rec, LostMessages) and rec.channel_id in targets:
                # keep the intact file's numbering: a lost cloud is a skipped scan
                for _ in range(rec.count):
                    index += 1
                    if self._selected(index):
                        yield self._skip(SkippedScan(index, f"{self.topic}#{index}",
                                                     f"message lost in a damaged {rec.where}"))
                continue
            if not isinstance(rec, Message) or rec.channel_id not in targets:
                continue
            index += 1
            if self._selected(index):
                yield self._skip(self._scan(index, rec))

    def _selected(self, index: int) -> bool:
        return index >= self.options.first and (self.options.last is None
                                                or index <= self.options.last)

    def _skip(self, item):
        """Record a skipped scan once (the pipeline may read the log twice) and pass it on."""
        if isinstance(item, SkippedScan) and item.index not in {s.index for s in self.report.skipped}:
            self.report.skipped.append(item)
        return item


    def _scan(self, index: int, rec: Message) -> Scan | SkippedScan:
        opts = self.options
        ch = self._channels[rec.channel_id]
        name = f"{self.topic}#{index} (log time {rec.log_time / 1e9:.6f} s)"
        try:
            msg = self._decoders.decode(ch, self._schemas.get(ch.schema_id), rec.data)
            arr, frame_id, stamp_ns, T_frame_cloud = _cloud_parts(self._kinds[self.topic], msg)
            sec, nsec = divmod(stamp_ns, 1_000_000_000)
            name = f"{self.topic}@{sec}.{nsec:09d}"
            T = np.eye(4) if frame_id.lstrip("/") == opts.map_frame.lstrip("/") else \
                self.tf.lookup(opts.map_frame, frame_id, stamp_ns)
            if T_frame_cloud is not None:
                T = T @ T_frame_cloud
            points = pc2.xyz(arr)
            labels = probs = gt = None
            if opts.prob_field:
                probs = self._probs(arr)
            else:
                labels, unknown = self._train_ids(arr, opts.label_field)
                self.report.unknown_labels += unknown
            if opts.gt_field:
                gt, unknown = self._train_ids(arr, opts.gt_field)
                self.report.unknown_gt_labels += unknown
            return Scan(points_sensor=points, T_world_sensor=T, stamp_s=stamp_ns / 1e9,
                        labels=labels, probs=probs, gt_labels=gt, index=index, name=name,
                        source=McapSource(topic=self.topic, frame_id=frame_id,
                                          stamp_ns=stamp_ns, log_time_ns=rec.log_time))
        except (TfError, pc2.CloudFormatError, ScanError) as e:
            return SkippedScan(index, name, str(e))
        except Exception as e:  # noqa: BLE001 - undecodable bytes raise anything
            return SkippedScan(index, name, f"cannot decode the message ({type(e).__name__}: {e})")

    def _train_ids(self, arr: np.ndarray, field_name: str) -> tuple[np.ndarray, int]:
        values = pc2.integer_labels(pc2.column(arr, field_name), field_name)
        if self.options.label_space == "raw":
            return raw_to_train(values)
        bad = (values < 0) | (values >= self.options.num_classes)
        return np.where(bad, 0, values).astype(np.int32), int(np.count_nonzero(bad))

    def _probs(self, arr: np.ndarray) -> np.ndarray:
        name = self.options.prob_field
        probs = pc2.column(arr, name)
        if probs.ndim != 2 or probs.shape[1] != self.options.num_classes:
            per = 1 if probs.ndim == 1 else probs.shape[1]
            raise pc2.CloudFormatError(f"probability field {name!r} has {per} value(s) per point; "
                                       f"the map has {self.options.num_classes} classes")
        return probs.astype(np.float32)
