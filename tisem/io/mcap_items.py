"""What a walk over MCAP data yields: `McapMessage` for each message record, `LostMessages`
where damaged data held messages, and the Schema and Channel records as `mcap` parses them.

Apart from the walk (`tisem.io.mcap_walk`), which finds the records, because the readers
consume these types (`tisem.io.bag_records` also makes them from bags that are not MCAP), and
one parsing serves the records inside chunks and those outside.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from mcap.opcode import Opcode
from mcap.records import Channel, Schema

from tisem.io.mcap_report import Loss, ReadReport
from tisem.io.mcap_summary import Malformed, opcode_name, parse_channel, parse_schema


@dataclass
class McapMessage:
    """A Message record: where it came from and whether a CRC vouched for its bytes."""

    channel_id: int
    log_time: int
    data: bytes
    crc_checked: bool  # its chunk's CRC matched (False outside chunks)


@dataclass
class LostMessages:
    """Yielded where damaged data held `count` messages of a channel, so that readers keep
    numbering messages as in the intact file. None: unknown (which channel, how many).
    `guessed`: counted from the damaged bytes themselves, which may put a message on another
    channel than its own (a flipped bit in a channel id), so the numbers after it may differ."""

    channel_id: int | None
    count: int | None
    where: str
    guessed: bool = False


@dataclass
class Unvouched:
    """A /tf_static message from the decodable start of a chunk that failed its checks,
    yielded after the chunk's loss, with its channel and schema (the chunk's own records, or
    those known before it). Nothing vouches for its bytes; `tisem.io.mcap_survey` uses it only
    where the recording holds the sensor's mount nowhere else, and then marks every scan."""

    where: str
    channel: Channel
    schema: Schema | None
    message: McapMessage


def is_static_tf(topic: str) -> bool:
    """Whether a topic is one of static transforms (/tf_static, a namespace's too)."""
    return topic.rstrip("/").endswith("tf_static")


def unvouched_statics(
    records: Iterable[tuple[int, bytes]], where: str, channels: dict[int, Channel]
) -> Iterator[Unvouched]:
    """The /tf_static messages among a damaged chunk's salvaged records (`channels`: those
    known before it, by id; the chunk's own Schema and Channel records are used, not kept)."""
    schemas: dict[int, Schema] = {}
    own: dict[int, Channel] = {}
    for opcode, content in records:
        try:
            rec = record_item(opcode, content, False, own)
        except Malformed:
            continue
        if isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, McapMessage):
            ch = own.get(rec.channel_id) or channels.get(rec.channel_id)
            if ch is not None and is_static_tf(ch.topic):
                yield Unvouched(where, ch, schemas.get(ch.schema_id), rec)


def unknown_loss(report: ReadReport, where: str, what: str) -> LostMessages:
    """Damage that held an unknown number of messages: reported, and the mark readers number
    the messages after it by (the scans after it are then suspect)."""
    report.losses.append(Loss(where, what, uncounted=True))
    return LostMessages(None, None, where)


def _message(content, crc_checked: bool) -> McapMessage:
    if len(content) < 22:
        raise Malformed(f"a message record of {len(content)} bytes (a message has at least 22)")
    channel_id, _, log_time, _ = struct.unpack_from("<HIQQ", content)
    return McapMessage(channel_id, log_time, bytes(content[22:]), crc_checked)


def record_item(
    opcode: int, content: bytes, crc_checked: bool, channels: dict[int, Channel]
) -> Schema | Channel | McapMessage | None:
    """The item of a Schema, Channel or Message record (a Channel is also added to `channels`,
    by id), None for any other record; `Malformed` when its bytes do not parse."""
    if opcode == Opcode.MESSAGE:
        return _message(content, crc_checked)
    if opcode not in (Opcode.SCHEMA, Opcode.CHANNEL):
        return None
    rec = parse_schema(content) if opcode == Opcode.SCHEMA else parse_channel(content)
    if isinstance(rec, Channel):
        channels[rec.id] = rec
    return rec


def chunk_items(
    records: Iterable[tuple[int, bytes]],
    checked: bool,
    where: str,
    channels: dict[int, Channel],
    report: ReadReport,
) -> Iterator[Schema | Channel | McapMessage | LostMessages]:
    """The items of the (opcode, content) records of the chunk `where` (`checked`: its CRC
    matched); a record that does not parse is a loss of that chunk."""
    for opcode, content in records:
        try:
            rec = record_item(opcode, content, checked, channels)
        except Malformed as e:
            loss = Loss(
                where,
                f"a {opcode_name(opcode)} record inside it is unparseable ({e})",
                uncounted=opcode == Opcode.MESSAGE,
            )
            report.losses.append(loss)
            if loss.uncounted:
                yield LostMessages(None, None, where)
            continue
        if rec is not None:
            yield rec
