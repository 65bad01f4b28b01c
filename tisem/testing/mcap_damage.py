"""Damaged MCAP files: small intact recordings to start from, and seeded mutations of them.
The recordings cover every layout the reader handles, among them a rosbag2 split compressed
message by message, in a folder whose metadata.yaml says so (read it as a user would, with
`tisem.io.bag_open.open_scan_reader`).

A mutation is either a byte edit of an intact file (a cut, a bit flip, a run of bytes, a length
field set to 2^32 or 2^63, a compression name, chunk index entries duplicated or deleted) at a
place its record layout names, or a recording written again with one cloud message changed (a
layout field that disagrees with the data, an empty cloud, labels that are no labels). Each
says whether a reader can detect it at all: flipping a cloud's byte order or a field's type
between two 4-byte types gives other values that are still a valid cloud.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tisem.synth.mcap_log import write_foxglove_log, write_synthetic_log

# the intact recordings: every layout the reader handles, ROS 2 and Foxglove, all with CRCs
# (without one a flipped byte in a cloud cannot be noticed, by any reader)
BASES = {
    "zstd": dict(compression="zstd"),
    "lz4": dict(compression="lz4"),
    "uncompressed": dict(compression="none"),
    "unchunked": dict(compression="none", chunked=False, data_crc=True),
    "no summary": dict(compression="zstd", indexed=False),
    "float labels": dict(compression="zstd", label_dtype="<f8"),
    "foxglove": dict(foxglove=True),
    # rosbag2's per-message compression: each message a zstd frame, the chunks uncompressed;
    # split files of a folder whose metadata.yaml says so (ZSTD_MESSAGES_FOLDER)
    "zstd messages": dict(compression="none", zstd_messages=True),
    # ... and as rosbag2's `fastwrite` preset writes it: no chunks, so no CRC but the data's
    "zstd messages unchunked": dict(
        compression="none", chunked=False, data_crc=True, zstd_messages=True
    ),
}
ZSTD_MESSAGES_FOLDER = "zstd_messages_bag"


def per_message_metadata(files: list[str]) -> str:
    """The metadata.yaml of a rosbag2 folder of MCAP `files` compressed message by message."""
    return (
        "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: mcap\n"
        f"  relative_file_paths: [{', '.join(files)}]\n"
        "  compression_format: zstd\n  compression_mode: MESSAGE\n"
    )


_COMMON = dict(n_scans=5, n_points=40, chunk_size=1500, tf_rate_hz=20.0, seed=7)
_NAMES = {
    0x01: "header",
    0x02: "footer",
    0x03: "schema",
    0x04: "channel",
    0x05: "message",
    0x06: "chunk",
    0x07: "message index",
    0x08: "chunk index",
    0x09: "attachment",
    0x0A: "attachment index",
    0x0B: "statistics",
    0x0C: "metadata",
    0x0D: "metadata index",
    0x0E: "summary offset",
    0x0F: "data end",
}
HUGE_VALUES = (2**32, 2**63, 2**64 - 1, 2**31, 0)


@dataclass
class Region:
    """One record (or the magic) of an intact file, and where its length-like fields are."""

    kind: str
    start: int
    end: int
    fields: dict[str, tuple[int, int]] = field(default_factory=dict)  # name -> (offset, size)


def layout(data: bytes) -> list[Region]:
    """The records of an intact MCAP file, front to back, with their fields' places."""
    summary_start = struct.unpack_from("<Q", data, len(data) - 37 + 9)[0]
    regions = [Region("magic", 0, 8)]
    pos = 8
    while pos < len(data) - 8:
        opcode, length = struct.unpack_from("<BQ", data, pos)
        kind = ("summary " if 0 < summary_start <= pos and opcode in (3, 4) else "") + _NAMES.get(
            opcode, f"opcode {opcode:#x}"
        )
        c = pos + 9
        fields = {"record length": (pos + 1, 8)}
        if opcode == 0x06:
            clen = struct.unpack_from("<I", data, c + 28)[0]
            fields.update(
                {
                    "uncompressed size": (c + 16, 8),
                    "crc": (c + 24, 4),
                    "compression length": (c + 28, 4),
                    "compression": (c + 32, clen),
                    "data length": (c + 32 + clen, 8),
                }
            )
        elif opcode == 0x07:
            fields["entries length"] = (c + 2, 4)
        elif opcode in (0x03, 0x04):
            fields["string length"] = (c + 2 if opcode == 0x03 else c + 4, 4)
        elif opcode == 0x08:
            fields.update(
                {
                    "chunk offset": (c + 16, 8),
                    "chunk length": (c + 24, 8),
                    "offsets length": (c + 32, 4),
                }
            )
        elif opcode == 0x0B:
            fields["counts length"] = (c + 42, 4)
        elif opcode == 0x02:
            fields = {
                "summary start": (c, 8),
                "summary offset start": (c + 8, 8),
                "summary crc": (c + 16, 4),
            }
        elif opcode == 0x0F:
            fields = {"data crc": (c, 4)}
        regions.append(Region(kind, pos, c + length, fields))
        pos = c + length
    regions.append(Region("tail magic", len(data) - 8, len(data)))
    return regions


@dataclass
class Base:
    name: str
    path: Path
    data: bytes
    regions: list[Region]
    options: dict


def _write(path: Path, options: dict, hook=None) -> None:
    if options.get("foxglove"):
        write_foxglove_log(
            path,
            **{k: options[k] for k in ("n_scans", "n_points", "seed", "chunk_size", "tf_rate_hz")},
        )
    else:
        write_synthetic_log(path, **options, cloud_hook=hook)


def _file_name(base: str) -> str:
    return f"{base.replace(' ', '_')}.mcap"


def case_folder(folder: Path, base: str) -> Path:
    """Where a recording made from `base` goes: `folder`, or for the per-message bases the
    rosbag2 folder in it whose metadata says its files compress message by message (made by
    `write_bases`)."""
    return folder / ZSTD_MESSAGES_FOLDER if BASES[base].get("zstd_messages") else folder


def write_bases(folder: Path) -> dict[str, Base]:
    """The intact recordings, written into `folder` (the per-message ones into their rosbag2
    folder there: read them with `tisem.io.bag_open.open_scan_reader`)."""
    bag = folder / ZSTD_MESSAGES_FOLDER
    bag.mkdir(parents=True, exist_ok=True)
    names = [_file_name(name) for name, o in BASES.items() if o.get("zstd_messages")]
    (bag / "metadata.yaml").write_text(per_message_metadata(names))
    out = {}
    for name, options in BASES.items():
        path = case_folder(folder, name) / _file_name(name)
        _write(path, {**_COMMON, **options})
        data = path.read_bytes()
        out[name] = Base(name, path, data, layout(data), {**_COMMON, **options})
    return out


@dataclass
class Mutation:
    """One damaged file: what was done, and how to make it."""

    base: str
    what: str
    detectable: bool
    data: bytes | None = None  # a byte edit of the base ...
    hook: Callable[[int, dict], dict] | None = None  # ... or the base written again with this

    def write(self, bases: dict[str, Base], path: Path) -> None:
        if self.data is not None:
            path.write_bytes(self.data)
        else:
            _write(path, bases[self.base].options, self.hook)


# ---- byte edits ------------------------------------------------------------------------------


def _pick(rng: np.random.Generator, items):
    return items[int(rng.integers(len(items)))]


def _cut(base: Base, rng) -> tuple[str, bytes]:
    r = _pick(rng, base.regions)
    at = _pick(
        rng, [r.start, r.start + 1, min(r.start + 9, r.end - 1), (r.start + r.end) // 2, r.end - 1]
    )
    return f"cut at byte {at} (in the {r.kind} at {r.start})", base.data[: max(at, 1)]


def _cut_anywhere(base: Base, rng) -> tuple[str, bytes]:
    at = int(rng.integers(1, len(base.data)))
    return f"cut at byte {at}", base.data[:at]


def _flip(base: Base, rng) -> tuple[str, bytes]:
    r = _pick(rng, base.regions)
    at, bit = int(rng.integers(r.start, r.end)), int(rng.integers(8))
    data = bytearray(base.data)
    data[at] ^= 1 << bit
    return f"bit {bit} of byte {at} flipped (in the {r.kind} at {r.start})", bytes(data)


def _overwrite(base: Base, rng) -> tuple[str, bytes]:
    r = _pick(rng, base.regions)
    n = int(rng.integers(1, 17))
    at = int(rng.integers(r.start, r.end))
    kind = _pick(rng, ["zeros", "0xff", "random"])
    run = {
        "zeros": bytes(n),
        "0xff": b"\xff" * n,
        "random": rng.integers(0, 256, n).astype(np.uint8).tobytes(),
    }[kind]
    data = bytearray(base.data)
    data[at : at + n] = run[: len(data) - at]
    return f"{n} byte(s) of {kind} written at byte {at} (in the {r.kind} at {r.start})", bytes(data)


def _length_field(base: Base, rng) -> tuple[str, bytes]:
    r = _pick(rng, [r for r in base.regions if r.fields])
    name = _pick(rng, sorted(r.fields))
    at, size = r.fields[name]
    if size not in (4, 8):
        return _overwrite(base, rng)
    old = int.from_bytes(base.data[at : at + size], "little")
    value = _pick(rng, [*HUGE_VALUES, old + 1, max(old - 1, 0)]) % (1 << (8 * size))
    data = bytearray(base.data)
    data[at : at + size] = value.to_bytes(size, "little")
    return f"{name} of the {r.kind} at {r.start} set to {value} (was {old})", bytes(data)


def _compression(base: Base, rng) -> tuple[str, bytes]:
    chunks = [r for r in base.regions if r.kind == "chunk" and r.fields["compression"][1]]
    if not chunks:
        return _flip(base, rng)
    r = _pick(rng, chunks)
    at, size = r.fields["compression"]
    name = _pick(rng, [b"zstx", b"ZSTD", b"gzip", b"lz4\0", b"bz2 ", b"lz5", b"LZ4", b"zst"])
    name = (name + b"    ")[:size]
    data = bytearray(base.data)
    data[at : at + size] = name
    return f"compression of the chunk at {r.start} renamed {name!r}", bytes(data)


def _index_entries(base: Base, rng) -> tuple[str, bytes]:
    """Duplicate, delete or swap chunk index entries; the footer's summary CRC recomputed,
    zeroed or left stale."""
    entries = [r for r in base.regions if r.kind == "chunk index"]
    footer = next(r for r in base.regions if r.kind == "footer")
    if len(entries) < 2:
        return _flip(base, rng)
    a, b = sorted(int(i) for i in rng.choice(len(entries), 2, replace=False))
    ra, rb = entries[a], entries[b]
    edit = _pick(rng, ["duplicate", "delete", "swap offsets"])
    data = bytearray(base.data)
    if edit == "duplicate":
        data[ra.end : ra.end] = base.data[ra.start : ra.end]
    elif edit == "delete":
        del data[ra.start : ra.end]
    else:
        off_a, off_b = ra.fields["chunk offset"][0], rb.fields["chunk offset"][0]
        data[off_a : off_a + 8], data[off_b : off_b + 8] = (
            base.data[off_b : off_b + 8],
            base.data[off_a : off_a + 8],
        )
    shift = len(data) - len(base.data)
    footer_at = footer.start + shift
    offset_start = struct.unpack_from("<Q", data, footer_at + 17)[0]
    if offset_start:
        struct.pack_into("<Q", data, footer_at + 17, offset_start + shift)
    crc_mode = _pick(rng, ["recomputed", "zeroed", "stale"])
    summary_start = struct.unpack_from("<Q", data, footer_at + 9)[0]
    crc = {
        "recomputed": zlib.crc32(data[summary_start : footer_at + 25]),
        "zeroed": 0,
        "stale": struct.unpack_from("<I", data, footer_at + 25)[0],
    }[crc_mode]
    struct.pack_into("<I", data, footer_at + 25, crc)
    return f"chunk index entry {a} ({edit} with entry {b}), summary CRC {crc_mode}", bytes(data)


BYTE_EDITS = (
    _cut,
    _cut_anywhere,
    _flip,
    _flip,
    _overwrite,
    _length_field,
    _length_field,
    _compression,
    _index_entries,
)


# ---- clouds written again with one message changed ------------------------------------------


def _replace_fields(msg: dict, field_name: str, **changes) -> dict:
    fields = [dict(f, **changes) if f["name"] == field_name else f for f in msg["fields"]]
    return dict(msg, fields=fields)


def _with_points(msg: dict, change: Callable[[np.ndarray], None]) -> dict:
    names = [f["name"] for f in msg["fields"]]
    codes = {7: "<f4", 8: "<f8", 4: "<u2", 6: "<u4"}
    dtype = np.dtype(
        {
            "names": names,
            "offsets": [f["offset"] for f in msg["fields"]],
            "formats": [codes[f["datatype"]] for f in msg["fields"]],
            "itemsize": msg["point_step"],
        }
    )
    arr = np.frombuffer(msg["data"], dtype).copy()
    change(arr)
    return dict(msg, data=arr.tobytes())


def _sized(msg: dict, width: int, step: int) -> dict:
    return dict(msg, width=width, point_step=step, row_step=width * step)


def _stamp_later(msg: dict, seconds: int) -> dict:
    stamp = dict(msg["header"]["stamp"], sec=msg["header"]["stamp"]["sec"] + seconds)
    return dict(msg, header=dict(msg["header"], stamp=stamp))


# (what, detectable, change of a PointCloud2 message dict)
LAYOUT_CHANGES: list[tuple[str, bool, Callable[[dict], dict]]] = [
    ("height 0", True, lambda m: dict(m, height=0)),
    ("width one smaller than the data", True, lambda m: _sized(m, m["width"] - 1, m["point_step"])),
    ("width one larger than the data", True, lambda m: _sized(m, m["width"] + 1, m["point_step"])),
    ("width 0 with data", True, lambda m: _sized(m, 0, m["point_step"])),
    ("point_step + 1", True, lambda m: _sized(m, m["width"], m["point_step"] + 1)),
    ("point_step - 1", True, lambda m: _sized(m, m["width"], m["point_step"] - 1)),
    ("point_step 0", True, lambda m: _sized(m, m["width"], 0)),
    ("point_step 2^31", True, lambda m: dict(m, point_step=2**31)),
    ("row_step + 1", True, lambda m: dict(m, row_step=m["row_step"] + 1)),
    ("row_step 2^32 - 1", True, lambda m: dict(m, row_step=2**32 - 1)),
    ("row_step 0 (means width x point_step)", True, lambda m: dict(m, row_step=0)),
    ("x overlapping y", True, lambda m: _replace_fields(m, "x", offset=2)),
    (
        "label past the point",
        True,
        lambda m: _replace_fields(m, "label", offset=m["point_step"] - 1),
    ),
    ("x datatype 0", True, lambda m: _replace_fields(m, "x", datatype=0)),
    ("x datatype 255", True, lambda m: _replace_fields(m, "x", datatype=255)),
    ("x as float64", True, lambda m: _replace_fields(m, "x", datatype=8)),
    ("x count 3", True, lambda m: _replace_fields(m, "x", count=3)),
    ("label count 2^32 - 1", True, lambda m: _replace_fields(m, "label", count=2**32 - 1)),
    ("label count 0 (means 1)", True, lambda m: _replace_fields(m, "label", count=0)),
    ("data one byte short", True, lambda m: dict(m, data=m["data"][:-1])),
    ("data one point short", True, lambda m: dict(m, data=m["data"][: -m["point_step"]])),
    ("data one byte long", True, lambda m: dict(m, data=m["data"] + b"\0")),
    ("data one point long", True, lambda m: dict(m, data=m["data"] + bytes(m["point_step"]))),
    ("data empty", True, lambda m: dict(m, data=b"")),
    ("an empty cloud", True, lambda m: dict(m, width=0, row_step=0, data=b"")),
    ("no label field", True, lambda m: _replace_fields(m, "label", name="labl")),
    ("empty frame_id", True, lambda m: dict(m, header=dict(m["header"], frame_id=""))),
    ("unknown frame_id", True, lambda m: dict(m, header=dict(m["header"], frame_id="x"))),
    ("stamp 1000 s later", True, lambda m: _stamp_later(m, 1000)),
    ("every point NaN", True, lambda m: _with_points(m, _all_nan)),
    # other values in a layout that is still valid: no reader can tell
    ("byte order flipped", False, lambda m: dict(m, is_bigendian=not m["is_bigendian"])),
    ("x as int32", False, lambda m: _replace_fields(m, "x", datatype=5)),
]


def _all_nan(arr: np.ndarray) -> None:
    for name in "xyz":
        arr[name] = np.nan


def _cloud_layout(base: Base, rng) -> Mutation:
    k = int(rng.integers(base.options["n_scans"]))
    what, detectable, change = _pick(rng, LAYOUT_CHANGES)

    def hook(i: int, msg: dict) -> dict:
        return change(msg) if i == k else msg

    return Mutation("zstd", f"cloud {k}: {what}", detectable, hook=hook)


def _float_labels(base: Base, rng) -> Mutation:
    k = int(rng.integers(base.options["n_scans"]))
    value = _pick(rng, [np.nan, np.inf, -np.inf, 1e300, -1.0, 0.5, 2.0**32, 1e20])
    points = sorted(int(i) for i in rng.choice(base.options["n_points"], 3, replace=False))

    def set_labels(arr: np.ndarray) -> None:
        arr["label"][points] = value

    def hook(i: int, msg: dict) -> dict:
        return _with_points(msg, set_labels) if i == k else msg

    return Mutation(
        "float labels", f"cloud {k}: labels of points {points} set to {value}", True, hook=hook
    )


def mcap_mutation(bases: dict[str, Base], rng: np.random.Generator, kind: int) -> Mutation:
    """Mutation number `kind` (cycling over byte edits and cloud changes) with `rng`'s choices."""
    makers = len(BYTE_EDITS) + 2
    kind %= makers
    if kind == len(BYTE_EDITS):
        return _cloud_layout(bases["zstd"], rng)
    if kind == len(BYTE_EDITS) + 1:
        return _float_labels(bases["float labels"], rng)
    name = _pick(rng, sorted(bases))
    what, data = BYTE_EDITS[kind](bases[name], rng)
    return Mutation(name, what, True, data=data)
