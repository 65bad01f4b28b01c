"""One entry for every recording `map_mcap.py` reads: path -> a scan reader.

    from tisem.io.bag_open import open_scan_reader
    reader = open_scan_reader("rosbag2_2024_05_01-12_00_00", McapOptions(gt_field="gt_label"))

What the path is decides the reader, by content (magic bytes, `metadata.yaml`), not by name:
- an MCAP file: tisem's damage-tolerant reader (`McapScanReader`);
- a rosbag2 folder of MCAP split files, uncompressed or compressed message by message (zstd):
  the same reader over its files in the order `metadata.yaml` lists them (still
  damage-tolerant: a message whose frame does not inflate is one lost message);
- any other rosbag2 folder (sqlite3 storage, per-file compression), a single `.db3` file, a
  ROS 1 `.bag`: the `rosbags` library reads the messages, tisem decodes the clouds and
  transforms the same way (damage part-way keeps the messages before it);
- what `rosbags` cannot open, or stops reading at damage, is read around it where the format
  allows: a ROS 1 bag record by record (`tisem.io.ros1_linear`: no index needed), a `.db3`
  row by row (`tisem.io.db3_rows`); a rosbag2 folder without usable metadata from its files;
- anything else is refused in one line naming what it is and how to convert it.
All give a `McapScanReader` (topic, frame_id, total, tf, report; iterate for scans).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

import yaml

from tisem.errors import DatasetError
from tisem.io.bag_records import ZSTD_MAGIC, SplitMcapRecords, split_files
from tisem.io.mcap_reader import McapOptions, McapScanReader
from tisem.io.mcap_summary import MAGIC as MCAP_MAGIC

SQLITE_MAGIC = b"SQLite format 3\x00"
ROS1_MAGIC = b"#ROSBAG V2.0"
STORAGES = ("mcap", "sqlite3")
CONVERT = (
    "`ros2 bag convert -i IN -o out.yaml` (ROS 2) or `rosbags-convert --src IN --dst "
    "OUT` (ROS 1 -> ROS 2)"
)


@dataclass(frozen=True)
class BagInput:
    """What a path holds: `kind` is mcap | mcap-split | rosbags, or ros1-linear | db3-rows
    (a ROS 1 bag read without its index, a .db3 row by row); `files` for mcap-split, and
    `zstd_messages` when each of their messages is a zstd frame of its own (None: unknown)."""

    path: Path
    kind: str
    what: str  # for messages, e.g. "rosbag2 folder (sqlite3, 2 files)"
    files: tuple[Path, ...] = ()
    zstd_messages: bool | None = False  # None: unknown, each cdr message tells by its bytes
    note: str = ""  # how it was read, for the report (a folder read without its metadata)
    storage: str = ""  # what rosbags reads: sqlite3 | mcap | ros1 (the other ways in need it)


def open_scan_reader(path: str | Path, options: McapOptions | None = None) -> McapScanReader:
    """The scan reader for the recording at `path` (module docstring); `DatasetError` with one
    line when it cannot be read."""
    found = identify(path)
    try:
        reader = _open_noted(found, options)
    except DatasetError as refusal:
        around = _read_around(found)
        if around is None:
            raise
        try:
            return _open_noted(around, options)
        except DatasetError as other:
            # read alike both ways, the recording is refused for what it holds (no transform
            # to the cloud's frame, no clouds): that refusal, not one blaming its pages
            if str(other) == _noted(str(refusal), around.note):
                raise refusal from None
            # (else it says what the records or rows held, and its note what was tried)
            raise
    return _past_the_damage(found, reader, options)


def _past_the_damage(found: BagInput, reader: McapScanReader, options) -> McapScanReader:
    """rosbags stops at the first damaged chunk of a ROS 1 bag, or page of a .db3 (or, in a
    ROS 1 bag, passes over one and yields fewer messages than the index lists); read record by
    record or row by row, what lies after it is read too. The reader that recovered more
    messages is kept, and on a tie the one that says where the damage was."""
    around = _read_around(found) if found.kind == "rosbags" else None
    if around is None or not reader.records.stopped:
        return reader
    try:
        other = _open_noted(around, options)
    except DatasetError:
        return reader
    got, ours = sum(other.report.messages.values()), sum(reader.report.messages.values())
    # rosbags fell short of its index without saying where: a walk that reads as much knows
    short = getattr(reader.records, "short", None) is not None
    return other if got > ours or (short and got == ours) else reader


def _read_around(found: BagInput) -> BagInput | None:
    """Another way into an input that `rosbags` cannot open (or read to its end), or None: a
    ROS 1 bag record by record, without its index (what a recording that did not close
    lacks); a `.db3`, or the one of a rosbag2 folder (whatever its metadata), row by row."""
    if found.kind != "rosbags" or importlib.util.find_spec("rosbags") is None:
        return None  # (without rosbags, the refusal says to install it)
    db3s = [found.path] if found.path.is_file() else split_files(found.path, ".db3")
    if found.storage == "sqlite3" and db3s:
        note = (
            f"rosbags cannot read {_listing(db3s)} (damaged database pages? its metadata?): its "
            f"messages were read row by row"
        )
        return BagInput(found.path, "db3-rows", found.what, tuple(db3s), note=note)
    if found.storage == "ros1":
        note = (
            "rosbags cannot use this ROS 1 bag's index, or stops at damage (a recording that "
            "did not close? a damaged chunk?): its records were read in file order; `rosbag "
            "reindex` rebuilds the index"
        )
        return BagInput(found.path, "ros1-linear", found.what, note=note)
    return None


def _open_noted(found: BagInput, options: McapOptions | None) -> McapScanReader:
    """`_open`, with how the input was read (`found.note`) in the report and in a refusal."""
    if not found.note:
        return _open(found, options)
    try:
        reader = _open(found, options)
    except DatasetError as e:
        raise DatasetError(_noted(str(e), found.note)) from None
    reader.report.notes.append(found.note)
    return reader


def _noted(refusal: str, note: str) -> str:
    """A refusal of an input read another way than its own, with how (`BagInput.note`)."""
    return f"{refusal} ({note})"


def _open(found: BagInput, options: McapOptions | None) -> McapScanReader:
    if found.kind == "mcap":
        return McapScanReader(found.path, options)
    if found.kind == "mcap-split":
        records = SplitMcapRecords(list(found.files), zstd_messages=found.zstd_messages)
        return McapScanReader(found.path, options, records=records)
    try:  # (the type stores of every other way in)
        import rosbags.highlevel  # noqa: F401 - only to say which package is missing

        from tisem.io.bag_records import RosbagRecords
        from tisem.io.db3_rows import Db3RowRecords
        from tisem.io.ros1_linear import Ros1LinearRecords
    except ImportError:
        raise DatasetError(
            f"{found.path}: reading a {found.what} needs the `rosbags` package: "
            f"pip install 'tisem[mcap]' (or pip install rosbags)"
        ) from None
    if found.kind == "ros1-linear":
        records = Ros1LinearRecords(found.path)
    elif found.kind == "db3-rows":
        records = Db3RowRecords(list(found.files))
    else:
        records = RosbagRecords(found.path, found.what, found.storage)
    return McapScanReader(found.path, options, records=records, decoders=records.decoders)


def identify(path: str | Path) -> BagInput:
    """What `path` is (`BagInput`), or `DatasetError` naming the format and the conversion."""
    path = Path(path)
    if path.is_dir():
        return _identify_folder(path)
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot open ({exc.strerror})") from None
    if head.startswith(SQLITE_MAGIC):
        return BagInput(path, "rosbags", "rosbag2 sqlite3 file", storage="sqlite3")
    if head.startswith(ROS1_MAGIC):
        return BagInput(path, "rosbags", "ROS 1 bag", storage="ros1")
    if head.startswith(b"#ROSBAG"):
        version = head.split()[1].decode(errors="replace") if len(head.split()) > 1 else "?"
        raise DatasetError(
            f"{path}: a ROS 1 bag of format {version} (tisem reads V2.0): run "
            f"`rosbag fix IN OUT`, then read OUT"
        )
    if head.startswith(ZSTD_MAGIC):
        raise DatasetError(
            f"{path}: a zstd-compressed file (a split of a per-file compressed "
            f"rosbag2 bag): give the bag folder (the one with metadata.yaml), or "
            f"decompress it with `zstd -d`"
        )
    if head.startswith(MCAP_MAGIC) or path.suffix == ".mcap":
        if _message_compressed_split(path):
            what = "split of a rosbag2 bag compressed message by message"
            return BagInput(path, "mcap-split", what, (path,), zstd_messages=True)
        return BagInput(path, "mcap", "MCAP file")
    raise DatasetError(
        f"{path}: not a recording tisem reads (no MCAP, SQLite or ROS 1 bag "
        f"header); tisem reads .mcap, rosbag2 folders, .db3 and ROS 1 .bag: "
        f"convert with {CONVERT}"
    )


def _bag_metadata(folder: Path) -> dict:
    meta_path = folder / "metadata.yaml"
    try:
        meta = yaml.safe_load(meta_path.read_text())["rosbag2_bagfile_information"]
        if not isinstance(meta, dict):
            raise TypeError("not a mapping")
    except OSError as exc:
        raise DatasetError(f"{meta_path}: cannot read ({exc.strerror})") from None
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as exc:  # (ValueError: not UTF-8)
        raise DatasetError(
            f"{meta_path}: not rosbag2 metadata ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0][:120] if str(exc) else ''}); "
            f"`ros2 bag reindex {folder}` writes it again"
        ) from None
    return meta


def _identify_folder(folder: Path) -> BagInput:
    if not (folder / "metadata.yaml").is_file():
        # what a recording that did not close leaves: rosbag2 writes the metadata at the end
        found = _without_metadata(folder, "no metadata.yaml")
        if found is not None:
            return found
        inside = sorted(
            p.name for p in folder.iterdir() if p.suffix in (".mcap", ".db3", ".bag", ".zstd")
        )[:4]
        hint = (
            f"; it holds {', '.join(inside)}: give one file, or write the metadata with "
            f"`ros2 bag reindex {folder}`"
            if inside
            else ""
        )
        raise DatasetError(f"{folder}: a folder without metadata.yaml is not a rosbag2 bag{hint}")
    try:
        meta = _bag_metadata(folder)
    except DatasetError:
        found = _without_metadata(folder, "metadata.yaml is damaged")
        if found is None:
            raise
        return found
    storage = meta.get("storage_identifier")
    if storage is None:  # (a damaged key)
        found = _without_metadata(folder, "metadata.yaml names no storage_identifier")
        if found is not None:
            return found
    if storage not in STORAGES:
        raise DatasetError(
            f"{folder}: rosbag2 storage {storage!r} is not readable here "
            f"(tisem reads {', '.join(STORAGES)}): convert with {CONVERT}"
        )
    names = meta.get("relative_file_paths") or []
    files = tuple(folder / Path(str(n)).name for n in names)
    missing = [f.name for f in files if not f.is_file()]
    if not files or missing:
        raise DatasetError(
            f"{folder}/metadata.yaml: "
            + (
                f"its files are missing: {', '.join(missing[:4])}"
                if missing
                else "it lists no files (relative_file_paths)"
            )
            + f"; `ros2 bag reindex {folder}` rewrites it from the files there"
        )
    compression = str(meta.get("compression_mode") or "none").lower()
    compressed = compression not in ("", "none")
    what = (
        f"rosbag2 folder ({storage}, {len(files)} file(s)"
        + (f", {compression} compression" if compressed else "")
        + ")"
    )
    if storage == "mcap" and not compressed:
        return BagInput(folder, "mcap-split", what, files)
    zstd = str(meta.get("compression_format") or "").lower() == "zstd"
    if storage == "mcap" and compression == "message" and zstd:
        return BagInput(folder, "mcap-split", what, files, zstd_messages=True)
    return BagInput(folder, "rosbags", what, storage=storage)


def _without_metadata(folder: Path, why: str) -> BagInput | None:
    """A rosbag2 folder whose metadata is missing or unreadable, read from its storage files:
    its MCAP files in split order, or its one `.db3`; None when it holds neither."""
    mcaps, db3s = split_files(folder, ".mcap"), split_files(folder, ".db3")
    hint = f"`ros2 bag reindex {folder}` rebuilds it"
    if mcaps and not db3s:
        note = (
            f"{why}: its {len(mcaps)} MCAP file(s) were read in split order "
            f"({_listing(mcaps)}); {hint}"
        )
        what = f"rosbag2 folder without metadata (mcap, {len(mcaps)} file(s))"
        return BagInput(folder, "mcap-split", what, tuple(mcaps), zstd_messages=None, note=note)
    if len(db3s) == 1 and not mcaps:
        note = f"{why}: its one file {db3s[0].name} was read; {hint}"
        return BagInput(db3s[0], "rosbags", "rosbag2 sqlite3 file", note=note, storage="sqlite3")
    if db3s and not mcaps:  # (rosbags reads split .db3 files only through the metadata)
        note = (
            f"{why}: its {len(db3s)} .db3 files were read in split order, row by row "
            f"({_listing(db3s)}); {hint}"
        )
        what = f"rosbag2 folder without metadata (sqlite3, {len(db3s)} file(s))"
        return BagInput(folder, "db3-rows", what, tuple(db3s), note=note)
    return None


def _listing(files: list[Path]) -> str:
    return ", ".join(p.name for p in files[:4]) + (", ..." if len(files) > 4 else "")


def _message_compressed_split(path: Path) -> bool:
    """Whether `path` is a split of a bag that compresses each message (its messages are zstd
    frames, which only the folder's metadata.yaml announces)."""
    if not (path.parent / "metadata.yaml").is_file():
        return False
    try:
        meta = _bag_metadata(path.parent)
    except DatasetError:
        return False  # a stray or damaged metadata.yaml: read the file itself
    return str(meta.get("compression_mode") or "").lower() == "message"
