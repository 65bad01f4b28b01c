"""MCAP chunks from untrusted bytes: the header, bounded decompression, the records inside.

A chunk is used only when everything about it agrees: its data fits its record, it inflates to
exactly the size it declares, its CRC (when present) matches, and its records fill it exactly.
Anything else raises `BadChunk` with the reason. Decompression never allocates from a length
it has not checked: a size the compressed frame declares must equal the chunk's, and otherwise
output is produced piece by piece and stopped as soon as it exceeds the declared size.
"""

from __future__ import annotations

import struct
import zlib
from collections import Counter
from dataclasses import dataclass

import lz4.frame
import zstandard
from mcap.opcode import Opcode

from tisem.io.mcap_summary import RECORD_HEADER, Fields, Malformed, parse_channel, parse_schema

COMPRESSIONS = ("", "zstd", "lz4")
MAX_CHUNK_BYTES = 1 << 31  # a chunk declaring more is taken as damaged
_PIECE = 1 << 24  # output per step of a bounded decompression
_CUT_STEP = 1 << 14  # input per step when inflating a cut chunk


class BadChunk(Exception):
    """A chunk whose bytes cannot be trusted (the message says why); it is skipped whole."""


# what the functions here raise on damaged bytes: BadChunk for what they check, and whatever
# the decompressors and parsers raise on the rest ("these bytes are damaged")
UNTRUSTED = (
    BadChunk,
    Malformed,
    zstandard.ZstdError,
    RuntimeError,
    struct.error,
    ValueError,
    OverflowError,
    EOFError,
)


@dataclass
class ChunkHeader:
    start_time: int
    end_time: int
    size: int  # uncompressed
    crc: int  # 0 = none
    compression: str
    data: memoryview  # may be shorter than `declared` in a cut chunk
    declared: int  # the compressed length the record gives


def chunk_header(buf, complete: bool = True) -> ChunkHeader:
    """The fields of a chunk record's content. In a complete chunk the data must fit."""
    f = Fields(buf, "chunk record")
    try:
        start, end, size, crc = f.u64(), f.u64(), f.u64(), f.u32()
        compression = f.text()
        declared = f.u64()
    except Malformed as e:
        raise BadChunk(str(e)) from None
    if complete and declared > f.left:
        raise BadChunk(f"its data claims {declared} bytes, the record holds {f.left}")
    return ChunkHeader(
        start, end, size, crc, compression, f.buf[f.pos : f.pos + declared], declared
    )


def _bounded(pieces, limit: int) -> bytes:
    """Join decompressed pieces, refusing as soon as they exceed `limit` bytes."""
    out = bytearray()
    for piece in pieces:
        out += piece
        if len(out) > limit:
            raise BadChunk(f"it inflates to more than the {limit} bytes it declares")
    return bytes(out)


def _zstd_pieces(data, complete: bool):
    if complete:
        yield from zstandard.ZstdDecompressor().read_to_iter(data, write_size=_PIECE)
        return
    # a cut frame: every complete block it still holds, fed in small steps so that the output
    # can be stopped early
    dobj = zstandard.ZstdDecompressor().decompressobj()
    for at in range(0, len(data), _CUT_STEP):
        yield dobj.decompress(bytes(data[at : at + _CUT_STEP]))


def _lz4_pieces(data):
    dec = lz4.frame.LZ4FrameDecompressor()
    piece = dec.decompress(bytes(data), max_length=_PIECE)
    while True:
        yield piece
        if dec.eof or dec.needs_input:
            return
        piece = dec.decompress(b"", max_length=_PIECE)


def inflate(head: ChunkHeader, complete: bool = True) -> bytes | memoryview:
    """The uncompressed records of a chunk (a prefix of them for a cut chunk)."""
    data, size = head.data, head.size
    if head.compression not in COMPRESSIONS:
        raise BadChunk(f"unknown compression {head.compression!r}")
    if size > MAX_CHUNK_BYTES:
        raise BadChunk(
            f"it declares {size} uncompressed bytes, more than a chunk can hold here "
            f"({MAX_CHUNK_BYTES})"
        )
    if head.compression == "":
        return data
    if head.compression == "zstd":
        framed = zstandard.frame_content_size(data) if complete else -1
        if framed == size:  # the frame and the chunk agree: one allocation of `size`
            return zstandard.ZstdDecompressor().decompress(data)
        if framed not in (-1, size):
            raise BadChunk(f"its zstd frame declares {framed} bytes, the chunk {size}")
        return _bounded(_zstd_pieces(data, complete), size)
    framed = lz4.frame.get_frame_info(data)["content_size"] if complete else 0
    if framed == size and size:
        return lz4.frame.decompress(data)
    if framed not in (0, size):
        raise BadChunk(f"its lz4 frame declares {framed} bytes, the chunk {size}")
    return _bounded(_lz4_pieces(data), size)


def stepped_prefix(dec, data, size: int) -> bytes:
    """What a stream decompressor with `max_length` (bz2's, lz4's) gives of `data` fed in
    steps, until it fails, ends, or gives `size` bytes: a failure loses only its step (bz2
    checks each block as it ends, so the blocks before a damaged one are whole)."""
    out = bytearray()
    try:
        for at in range(0, len(data), _CUT_STEP):
            out += dec.decompress(bytes(data[at : at + _CUT_STEP]), max_length=size + 1)
            while len(out) <= size and not dec.eof and not dec.needs_input:
                out += dec.decompress(b"", max_length=size + 1 - len(out))
            if len(out) >= size or dec.eof:
                break
    except (OSError, EOFError, RuntimeError, ValueError):
        pass  # (the damage: what came before it is kept)
    return bytes(out[:size])


def _prefix(head: ChunkHeader) -> bytes | memoryview:
    """What a chunk that failed its checks inflates to before its damage stops the
    decompressor, at most its declared size. That is the chunk's first records, and where
    the decompressor does not notice the damage (a flipped literal), the damaged bytes too."""
    if head.compression == "":
        return head.data[: head.size]
    out = bytearray()
    try:
        if head.compression == "zstd":  # (read in bounded pieces: an error loses its piece)
            reader = zstandard.ZstdDecompressor().stream_reader(bytes(head.data))
            while len(out) < head.size and (
                piece := reader.read(min(_CUT_STEP, head.size - len(out)))
            ):
                out += piece
        elif head.compression == "lz4":
            return stepped_prefix(lz4.frame.LZ4FrameDecompressor(), head.data, head.size)
    except UNTRUSTED:
        pass  # (the damage: what came before it is kept)
    return bytes(out[: head.size])


def salvaged_records(head: ChunkHeader) -> list[tuple[int, memoryview]]:
    """(opcode, content) of the whole records at the start of a chunk that failed its checks
    (`_prefix`). Nothing vouches for their bytes: a flipped bit can also decompress into
    wrong bytes without an error, before the decompressor notices. See
    `tisem.io.mcap_items.Unvouched` for the one use made of them."""
    if head.compression not in COMPRESSIONS or head.size > MAX_CHUNK_BYTES:
        return []
    return inner_records(_prefix(head), complete=False)


def inner_records(data, complete: bool = True) -> list[tuple[int, memoryview]]:
    """(opcode, content) of the records inside a chunk. In a complete chunk a record that
    overruns it means corruption; in a cut one it is where the cut was."""
    out, pos, view = [], 0, memoryview(data)
    while pos + RECORD_HEADER <= len(view):
        opcode, length = struct.unpack_from("<BQ", view, pos)
        end = pos + RECORD_HEADER + length
        if end > len(view):
            break
        out.append((opcode, view[pos + RECORD_HEADER : end]))
        pos = end
    if complete and pos != len(view):
        raise BadChunk("its records do not fill it exactly")
    return out


def checked_records(head: ChunkHeader) -> tuple[list[tuple[int, memoryview]], bool]:
    """(records, crc_checked) of a complete chunk; `BadChunk` when anything disagrees."""
    data = inflate(head)
    if len(data) != head.size:
        raise BadChunk(f"it inflates to {len(data)} bytes, not the {head.size} it declares")
    if head.crc and zlib.crc32(data) != head.crc:
        raise BadChunk("its CRC does not match: corrupted bytes")
    return inner_records(data), bool(head.crc)


def messages_in_damaged(head: ChunkHeader) -> Counter | None:
    """Messages per channel a chunk that failed its checks still shows, when its records still
    parse whole (the damage is inside message contents); None when they cannot be counted.

    A chunk holds schema, channel and message records. In one that failed its checks, a
    record of another opcode, or a schema or channel record that does not parse, is a record
    the damage hit (a flipped bit in compressed data can rewrite several records' opcodes),
    so a count of its message records would miss what it was: None."""
    try:
        data = inflate(head)
        records = inner_records(data)
    except (BadChunk, zstandard.ZstdError, RuntimeError, ValueError, struct.error):
        return None
    counts = Counter()
    for opcode, content in records:
        if opcode == Opcode.MESSAGE:
            if len(content) < 22:
                return None
            counts[struct.unpack_from("<H", content)[0]] += 1
            continue
        try:
            if opcode == Opcode.SCHEMA:
                parse_schema(content)
            elif opcode == Opcode.CHANNEL:
                parse_channel(content)
            else:
                return None
        except Malformed:
            return None
    return counts
