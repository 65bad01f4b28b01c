"""One entry for every recording `map_mcap.py` reads: path -> a scan reader.

    from tisem.io.bag_open import open_scan_reader
    reader = open_scan_reader("rosbag2_2024_05_01-12_00_00", McapOptions(gt_field="gt_label"))

What the path is decides the reader, by content (magic bytes, `metadata.yaml`), not by name:
- an MCAP file: tisem's damage-tolerant reader (`McapScanReader`);
- a rosbag2 folder of uncompressed MCAP split files: the same reader over its files in the
  order `metadata.yaml` lists them (still damage-tolerant);
- any other rosbag2 folder (sqlite3 storage, per-message or per-file compression), a single
  `.db3` file, a ROS 1 `.bag`: the `rosbags` library reads the messages, tisem decodes the
  clouds and transforms the same way;
- anything else is refused in one line naming what it is and how to convert it.
All give a `McapScanReader` (topic, frame_id, total, tf, report; iterate for scans).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import yaml

from tisem.errors import DatasetError
from tisem.io.mcap_reader import McapOptions, McapScanReader
from tisem.io.mcap_summary import MAGIC as MCAP_MAGIC

SQLITE_MAGIC = b"SQLite format 3\x00"
ROS1_MAGIC = b"#ROSBAG V2.0"
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
STORAGES = ("mcap", "sqlite3")
CONVERT = (
    "`ros2 bag convert -i IN -o out.yaml` (ROS 2) or `rosbags-convert --src IN --dst "
    "OUT` (ROS 1 -> ROS 2)"
)


@dataclass(frozen=True)
class BagInput:
    """What a path holds: `kind` is mcap | mcap-split | rosbags; `files` for mcap-split."""

    path: Path
    kind: str
    what: str  # for messages, e.g. "rosbag2 folder (sqlite3, 2 files)"
    files: tuple[Path, ...] = ()


def open_scan_reader(path: str | Path, options: McapOptions | None = None) -> McapScanReader:
    """The scan reader for the recording at `path` (module docstring); `DatasetError` with one
    line when it cannot be read."""
    found = identify(path)
    if found.kind == "mcap":
        return McapScanReader(found.path, options)
    if found.kind == "mcap-split":
        from tisem.io.bag_records import SplitMcapRecords

        return McapScanReader(found.path, options, records=SplitMcapRecords(list(found.files)))
    try:
        import rosbags.highlevel  # noqa: F401 - only to say which package is missing

        from tisem.io.bag_records import RosbagRecords
    except ImportError:
        raise DatasetError(
            f"{found.path}: reading a {found.what} needs the `rosbags` package: "
            f"pip install 'tisem[mcap]' (or pip install rosbags)"
        ) from None
    records = RosbagRecords(found.path, found.what)
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
        return BagInput(path, "rosbags", "rosbag2 sqlite3 file")
    if head.startswith(ROS1_MAGIC):
        return BagInput(path, "rosbags", "ROS 1 bag")
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
        _refuse_message_compressed_split(path)
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
    except (yaml.YAMLError, KeyError, TypeError) as exc:
        raise DatasetError(
            f"{meta_path}: not rosbag2 metadata ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0][:120] if str(exc) else ''}); "
            f"`ros2 bag reindex {folder}` writes it again"
        ) from None
    return meta


def _identify_folder(folder: Path) -> BagInput:
    if not (folder / "metadata.yaml").is_file():
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
    meta = _bag_metadata(folder)
    storage = meta.get("storage_identifier")
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
    return BagInput(folder, "rosbags", what)


def _refuse_message_compressed_split(path: Path) -> None:
    """A split of a bag that compresses each message: its messages are zstd frames, which
    only the folder's metadata.yaml announces."""
    meta_path = path.parent / "metadata.yaml"
    if not meta_path.is_file():
        return
    try:
        meta = _bag_metadata(path.parent)
    except DatasetError:
        return  # a stray or damaged metadata.yaml: read the file itself
    if str(meta.get("compression_mode") or "").lower() == "message":
        raise DatasetError(
            f"{path}: a split of a bag whose messages are compressed one by one "
            f"(metadata.yaml beside it); give the folder {path.parent} instead"
        )
