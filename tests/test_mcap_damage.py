"""Damaged recordings: cut short, bad chunks, no index, no CRC, undecodable messages.

Each test writes a small log, damages its bytes, and checks that every intact message is
recovered, the damaged part is reported (never a traceback), and no scan carries wrong data.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import zlib

import numpy as np
import pytest
from mcap.reader import make_reader

from tisem.errors import DatasetError, SkippedScan
from tisem.io.mcap_reader import McapOptions, McapScanReader
from tisem.labels import raw_to_train
from tisem.scan import Scan
from tisem.synth.mcap_log import write_synthetic_log
from tisem.testing.mcap_damage import layout, per_message_metadata

N_SCANS = 6


def top_level_records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of each record after the magic, up to the data end."""
    out, pos = [], 8
    while pos < len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        out.append((opcode, pos, pos + 9 + length))
        if opcode == 0x0F:  # data end: the summary follows
            break
        pos += 9 + length
    return out


def check_scans_against_truth(items, truth) -> list[int]:
    """Every Scan equals the truth of its index; returns the indexes of the Scans."""
    got = []
    for s in items:
        if isinstance(s, Scan):
            k = s.index
            assert np.abs(s.T_world_sensor - truth["T_world_sensor"][k]).max() < 1e-9, k
            assert np.array_equal(s.labels, raw_to_train(truth["points"][k]["label"])[0]), k
            assert np.array_equal(s.points_sensor[:, 0], truth["points"][k]["x"]), k
            got.append(k)
    return got


def cut(src, dst, size: int) -> None:
    dst.write_bytes(src.read_bytes()[:size])


@pytest.mark.parametrize("fraction", [0.3, 0.62, 0.97])
def test_cut_unchunked_file_recovers_every_complete_message(tmp_path, fraction):
    full = tmp_path / "full.mcap"
    truth = write_synthetic_log(
        full, n_scans=N_SCANS, n_points=300, chunked=False, compression="none"
    )
    data = full.read_bytes()
    size = int(len(data) * fraction)
    messages = [r for r in top_level_records(data) if r[0] == 0x05]
    complete = [r for r in messages if r[2] <= size]
    clouds = [r for r in complete if len(data[r[1] : r[2]]) > 2000]  # clouds are the big ones
    cut(full, tmp_path / "cut.mcap", size)

    reader = McapScanReader(tmp_path / "cut.mcap")
    items = list(reader)
    assert sum(reader.report.messages.values()) == len(complete)
    assert check_scans_against_truth(items, truth) == list(range(len(clouds)))
    assert any("cut short" in line for line in reader.report.lines())


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
@pytest.mark.parametrize("fraction", [0.5, 0.999])
def test_cut_chunked_file(tmp_path, compression, fraction):
    full = tmp_path / "full.mcap"
    truth = write_synthetic_log(
        full, n_scans=N_SCANS, n_points=600, compression=compression, chunk_size=8_000
    )  # about one chunk per scan
    with open(full, "rb") as f:
        summary = make_reader(f).get_summary()
    size = int(full.stat().st_size * fraction)
    whole_chunks = [
        c for c in summary.chunk_indexes if c.chunk_start_offset + c.chunk_length <= size
    ]
    clouds_in_whole_chunks = sum(
        any(c.message_start_time <= t + 35_000_000 <= c.message_end_time for c in whole_chunks)
        for t in truth["stamps_ns"]
    )
    cut(full, tmp_path / "cut.mcap", size)

    reader = McapScanReader(tmp_path / "cut.mcap")
    items = list(reader)
    got = check_scans_against_truth(items, truth)
    assert got == list(range(len(got))) and len(got) >= clouds_in_whole_chunks
    if fraction > 0.99:  # only the summary is gone: nothing lost
        assert len(got) == N_SCANS
    lines = reader.report.lines()
    assert any("no summary section" in line for line in lines)
    if fraction < 0.99:
        assert any("cut short" in line for line in lines)


@pytest.mark.parametrize("size", [8, 20, 60])
def test_files_cut_before_any_cloud_give_a_clear_error(tmp_path, size):
    full = tmp_path / "full.mcap"
    write_synthetic_log(full, n_scans=2, n_points=50)
    cut(full, tmp_path / "cut.mcap", size)
    with pytest.raises(
        DatasetError, match="no point-cloud messages found.*the file is damaged.*cut"
    ):
        McapScanReader(tmp_path / "cut.mcap")


@pytest.mark.parametrize(
    "content,message",
    [
        (b"", "the file is empty"),
        (b"PK\x03\x04 not an mcap at all", "not an MCAP file"),
    ],
)
def test_empty_and_foreign_files(tmp_path, content, message):
    (tmp_path / "x.mcap").write_bytes(content)
    with pytest.raises(DatasetError, match=message):
        McapScanReader(tmp_path / "x.mcap")
    with pytest.raises(DatasetError, match="cannot open"):
        McapScanReader(tmp_path / "missing.mcap")


def chunk_of_scan(path, truth, k):
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    log_time = truth["stamps_ns"][k] + 35_000_000
    (chunk,) = [
        c for c in summary.chunk_indexes if c.message_start_time <= log_time <= c.message_end_time
    ]
    return chunk


def flip(path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x5A
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
@pytest.mark.parametrize("summary", ["intact", "cut off"])
def test_a_chunk_with_a_bad_crc_is_skipped_and_reported(tmp_path, compression, summary):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(
        path, n_scans=N_SCANS, n_points=600, compression=compression, chunk_size=8_000
    )
    chunk = chunk_of_scan(path, truth, 2)
    flip(path, chunk.chunk_start_offset + chunk.chunk_length - 100)  # inside its data
    if summary == "cut off":  # linear reading; the message index records still count the loss
        data = path.read_bytes()
        end = [r for r in top_level_records(data) if r[0] == 0x0F][0][1]
        path.write_bytes(data[:end])
    reader = McapScanReader(path)
    items = list(reader)
    assert [i.index for i in items] == list(range(N_SCANS))  # numbering as in the intact file
    assert check_scans_against_truth(items, truth) == [0, 1, 3, 4, 5]
    assert isinstance(items[2], SkippedScan)
    assert f"chunk at byte {chunk.chunk_start_offset}" in items[2].reason
    (loss,) = reader.report.losses if summary == "intact" else reader.report.losses[:1]
    assert loss.topics["/velodyne_points"] == 1 and "chunk skipped" in loss.what
    assert "1 on /velodyne_points" in loss.line()


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
@pytest.mark.parametrize("mount", ["from the damaged chunk", "given with --static-tf"])
def test_a_damaged_first_chunk_s_sensor_mount_is_read_and_every_scan_marked(
    tmp_path, compression, mount
):
    """The first chunk holds /tf_static, the sensor's mount, and nothing else does: a byte
    damaged in its first cloud would refuse the whole recording. The mount is read from the
    records before the damage; the first scan is lost, the others are mapped as in the intact
    file and marked (nothing vouches for the mount). A mount the user gives is used instead,
    and nothing is marked."""
    from tisem.io.tf import matrix_to_quat
    from tisem.synth.mcap_log import T_BASE_LIDAR

    path = tmp_path / "log.mcap"
    # (clouds of several compressed blocks, as real ones are: the blocks before the damaged
    # one still inflate)
    truth = write_synthetic_log(
        path, n_scans=N_SCANS, n_points=12_000, compression=compression, chunk_size=8_000
    )
    chunk = chunk_of_scan(path, truth, 0)
    chunks = [start for op, start, _ in top_level_records(path.read_bytes()) if op == 0x06]
    assert chunk.chunk_start_offset == chunks[0]  # the first: /tf_static's
    flip(path, chunk.chunk_start_offset + chunk.chunk_length - 100)  # inside cloud 0's data
    given = ()
    if mount == "given with --static-tf":
        q = matrix_to_quat(T_BASE_LIDAR[:3, :3])
        given = (("base_link", "velodyne", *T_BASE_LIDAR[:3, 3], *q),)
    reader = McapScanReader(path, McapOptions(static_tf=given))
    items = list(reader)
    assert isinstance(items[0], SkippedScan)
    assert check_scans_against_truth(items, truth) == list(range(1, N_SCANS))
    if given:
        assert reader.report.suspect == {}
        return
    assert sorted(reader.report.suspect) == list(range(1, N_SCANS))
    (why,) = set(reader.report.suspect.values())
    assert why == (
        "its pose uses a static transform read from a damaged chunk, whose bytes nothing "
        f"vouches for (base_link -> velodyne from the chunk at byte {chunk.chunk_start_offset}"
        f" (log time {chunk.message_start_time / 1e9:.3f}-{chunk.message_end_time / 1e9:.3f}"
        " s)); --static-tf gives it instead"
    )


def test_a_damaged_first_chunk_s_sensor_mount_in_a_rosbag2_folder(tmp_path):
    """The same in a rosbag2 folder of MCAP files, read file after file: the mount read from
    the damaged chunk goes through that reader too."""
    from tisem.io.bag_open import open_scan_reader

    folder = tmp_path / "bag"
    folder.mkdir()
    path = folder / "bag_0.mcap"
    truth = write_synthetic_log(
        path, n_scans=N_SCANS, n_points=12_000, compression="zstd", chunk_size=8_000
    )
    chunk = chunk_of_scan(path, truth, 0)
    flip(path, chunk.chunk_start_offset + chunk.chunk_length - 100)
    reader = open_scan_reader(folder)
    items = list(reader)
    assert isinstance(items[0], SkippedScan)
    assert check_scans_against_truth(items, truth) == list(range(1, N_SCANS))
    assert sorted(reader.report.suspect) == list(range(1, N_SCANS))
    assert "a static transform read from a damaged chunk" in reader.report.suspect[1]


@pytest.mark.parametrize("summary", ["intact", "cut off"])
def test_a_damaged_chunk_length_field_loses_at_most_that_chunk(tmp_path, summary):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=600, chunk_size=8_000)
    chunk = chunk_of_scan(path, truth, 4)
    data = bytearray(path.read_bytes())
    if summary == "cut off":
        data = data[: [r for r in top_level_records(bytes(data)) if r[0] == 0x0F][0][1]]
    data[chunk.chunk_start_offset + 1 : chunk.chunk_start_offset + 9] = b"\xff" * 8  # its length
    path.write_bytes(bytes(data))
    reader = McapScanReader(path)
    items = list(reader)
    if summary == "intact":  # the chunk index gives the length, and the chunk checks out
        assert check_scans_against_truth(items, truth) == list(range(N_SCANS))
        assert (
            "its record header is damaged; the chunk index gives its length"
            in reader.report.lines()[0]
        )
    else:  # the next chunk is found in the bytes; the loss is counted
        assert check_scans_against_truth(items, truth) == [0, 1, 2, 3, 5]
        assert isinstance(items[4], SkippedScan) and items[4].index == 4
        (loss,) = [x for x in reader.report.losses if "reading went on" in x.what]
        assert loss.topics["/velodyne_points"] == 1 and "past the end of the file" in loss.what
        assert not reader.report.suspect


@pytest.mark.parametrize(
    "variant",
    [
        dict(indexed=False),
        dict(chunked=False),
        dict(indexed=False, chunked=False, compression="lz4"),
    ],
)
def test_files_without_index_or_chunks_read_completely(tmp_path, variant):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=200, **variant)
    reader = McapScanReader(path)
    assert check_scans_against_truth(list(reader), truth) == list(range(N_SCANS))
    assert not reader.report.losses
    assert any("read linearly" in n for n in reader.report.notes)


def test_chunks_without_crc_are_flagged(tmp_path):
    path = tmp_path / "log.mcap"
    write_synthetic_log(path, n_scans=2, n_points=50, crcs=False)
    reader = McapScanReader(path)
    assert any("carry no CRC" in line for line in reader.report.lines())


def test_an_undecodable_cloud_is_skipped_with_the_reason(tmp_path):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=4, n_points=100, compression="none", crcs=False)
    data = bytearray(path.read_bytes())
    frame = struct.pack("<I", 9) + b"velodyne\x00"  # a CDR string
    hits = [i for i in range(len(data)) if data.startswith(frame, i)]
    at = hits[3] + len(frame) + 3  # cloud 2 (after /tf_static)
    data[at : at + 16] = b"\xff" * 16  # height, width, fields length
    path.write_bytes(bytes(data))
    items = list(McapScanReader(path))
    assert check_scans_against_truth(items, truth) == [0, 1, 3]
    assert isinstance(items[2], SkippedScan) and items[2].index == 2
    assert "decode" in items[2].reason or "data has" in items[2].reason


def test_lost_clouds_outside_first_last_are_not_reported(tmp_path):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=600, chunk_size=8_000)
    chunk = chunk_of_scan(path, truth, 1)
    flip(path, chunk.chunk_start_offset + chunk.chunk_length - 100)
    reader = McapScanReader(path, McapOptions(first=2))
    assert [i.index for i in reader] == [2, 3, 4, 5] and reader.total == 4


# ---- lengths taken on trust, the summary and its index, CRCs -------------------------------


def regions_of(path, kind):
    return [r for r in layout(path.read_bytes()) if r.kind == kind]


def set_field(path, region, name, value) -> None:
    at, size = region.fields[name]
    data = bytearray(path.read_bytes())
    data[at : at + size] = value.to_bytes(size, "little")
    path.write_bytes(bytes(data))


def refresh_summary_crc(path) -> None:
    """Recompute the footer's summary CRC after editing the summary (a consistent index)."""
    data = bytearray(path.read_bytes())
    footer = len(data) - 37
    start = struct.unpack_from("<Q", data, footer + 9)[0]
    struct.pack_into("<I", data, footer + 25, zlib.crc32(data[start : footer + 25]))
    path.write_bytes(bytes(data))


def read_with_memory_limit(path, limit_mb: int = 1500) -> dict:
    """Read in a child process whose address space is limited: a length taken on trust that
    allocates gigabytes is a MemoryError there (what it was under a 3 GB limit)."""
    code = (
        f"import json, resource; resource.setrlimit(resource.RLIMIT_AS, ({limit_mb << 20},"
        f" {limit_mb << 20}))\n"
        "from tisem.io.mcap_reader import McapScanReader\n"
        "from tisem.scan import Scan\n"
        f"r = McapScanReader({str(path)!r})\n"
        "items = list(r)\n"
        "print(json.dumps({'scans': [s.index for s in items if isinstance(s, Scan)],"
        " 'lines': r.report.lines()}))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


@pytest.mark.parametrize(
    "kind,name,value",
    [
        ("summary schema", "record length", 2**32),  # was a MemoryError under 3 GB
        ("summary channel", "string length", 2**32 - 1),
        ("chunk index", "offsets length", 2**31),
        ("statistics", "counts length", 2**32 - 1),
        ("footer", "summary start", 2**63),
    ],
)
def test_huge_lengths_in_the_summary_only_cost_the_summary(tmp_path, kind, name, value):
    path = tmp_path / "log.mcap"
    write_synthetic_log(path, n_scans=N_SCANS, n_points=200, chunk_size=3_000)
    set_field(path, regions_of(path, kind)[0], name, value)
    refresh_summary_crc(path)  # the CRC alone would already refuse the summary
    got = read_with_memory_limit(path)
    assert got["scans"] == list(range(N_SCANS))
    assert any(
        line.startswith("summary section: ")
        and "it was not used and the file was read from its data" in line
        for line in got["lines"]
    )


@pytest.mark.parametrize(
    "name,value",
    [
        ("uncompressed size", 2**63),  # an OverflowError
        ("uncompressed size", 2**40),
        ("data length", 2**64 - 1),
        ("compression length", 2**32 - 1),
    ],
)
def test_huge_lengths_in_a_chunk_lose_that_chunk_only(tmp_path, name, value):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=200, chunk_size=3_000)
    chunk = chunk_of_scan(path, truth, 2)
    (region,) = [r for r in regions_of(path, "chunk") if r.start == chunk.chunk_start_offset]
    set_field(path, region, name, value)
    got = read_with_memory_limit(path)
    assert got["scans"] == [0, 1, 3, 4, 5]
    assert any(
        line.startswith(f"chunk at byte {chunk.chunk_start_offset}")
        and "chunk skipped" in line
        and "1 on /velodyne_points" in line
        for line in got["lines"]
    )


def test_a_lost_chunk_is_counted_from_the_data_not_from_index_offsets(tmp_path):
    """The chunk index's message index offsets pointing anywhere (a seek error before) do not
    matter: what a lost chunk held is counted from the records after it in the data."""
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=200, chunk_size=3_000)
    chunk = chunk_of_scan(path, truth, 3)
    flip(path, chunk.chunk_start_offset + chunk.chunk_length - 50)
    data = bytearray(path.read_bytes())
    for entry in regions_of(path, "chunk index"):
        at = entry.fields["offsets length"][0] + 4
        n = struct.unpack_from("<I", data, at - 4)[0] // 10
        for k in range(n):  # (u16 channel, u64 offset) pairs
            struct.pack_into("<Q", data, at + 10 * k + 2, 2**64 - 1 - k)
    path.write_bytes(bytes(data))
    refresh_summary_crc(path)
    reader = McapScanReader(path)
    items = list(reader)
    assert check_scans_against_truth(items, truth) == [0, 1, 2, 4, 5]
    assert isinstance(items[3], SkippedScan)
    (loss,) = [x for x in reader.report.losses if "chunk skipped" in x.what]
    assert loss.topics["/velodyne_points"] == 1


def test_a_summary_whose_crc_fails_is_not_used(tmp_path):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=200, chunk_size=3_000)
    entry = regions_of(path, "chunk index")[1]
    set_field(path, entry, "chunk offset", 8)  # an index that points elsewhere
    reader = McapScanReader(path)
    assert check_scans_against_truth(list(reader), truth) == list(range(N_SCANS))
    assert reader.report.lines()[0] == (
        "summary section: the summary section's CRC does not match (corrupted bytes); it was "
        "not used and the file was read from its data"
    )


@pytest.mark.parametrize("edit", ["duplicate", "delete"])
def test_a_damaged_chunk_index_neither_duplicates_nor_renumbers_a_scan(tmp_path, edit):
    """Entries duplicated or deleted in a summary whose CRC was made to match: the data is
    read, each cloud once and numbered by its place in the data, and the disagreement said."""
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=200, chunk_size=3_000)
    entries = regions_of(path, "chunk index")
    data = bytearray(path.read_bytes())
    first = entries[0]
    shift = first.end - first.start
    if edit == "duplicate":
        data[first.end : first.end] = data[first.start : first.end]
    else:
        del data[first.start : first.end]
        shift = -shift
    footer = len(data) - 37
    offset_start = struct.unpack_from("<Q", data, footer + 17)[0]
    struct.pack_into("<Q", data, footer + 17, offset_start + shift)
    path.write_bytes(bytes(data))
    refresh_summary_crc(path)
    reader = McapScanReader(path)
    items = list(reader)
    assert [i.index for i in items] == list(range(N_SCANS))
    assert check_scans_against_truth(items, truth) == list(range(N_SCANS))
    (line,) = [x.line() for x in reader.report.losses]
    what = (
        "1 duplicated entry for the chunk(s) at byte"
        if edit == "duplicate"
        else "no entry for the chunk(s) at byte"
    )
    assert line.startswith("chunk index (summary section): disagrees with the data (" + what)
    assert line.endswith("): the file was read from its data")


def test_a_flipped_bit_in_an_unchunked_file_marks_its_scans_suspect(tmp_path):
    """Records outside chunks have no CRC of their own; the data section's CRC (in the
    data-end record) says that something is corrupted, not where: every scan is marked."""
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(
        path, n_scans=4, n_points=200, chunked=False, compression="none", data_crc=True
    )
    clouds = [r for r in regions_of(path, "message") if r.end - r.start > 2000]
    flip(path, clouds[2].end - 100)  # a point of cloud 2
    reader = McapScanReader(path)
    items = list(reader)
    assert [type(i).__name__ for i in items] == ["Scan"] * 4
    assert sorted(reader.report.suspect) == [0, 1, 2, 3]
    assert check_scans_against_truth([i for i in items if i.index != 2], truth) == [0, 1, 3]
    lines = reader.report.lines()
    assert lines[0] == (
        "data section: its CRC (in the data-end record) does not match: some "
        "bytes are corrupted; messages without a CRC of their own cannot be "
        "told apart from damaged ones (their scans are marked suspect)"
    )
    assert "scan(s) 0-3 mapped but suspect: the data section's CRC does not match" in lines[-1]
    # intact, the same file is clean
    write_synthetic_log(
        path, n_scans=4, n_points=200, chunked=False, compression="none", data_crc=True
    )
    assert McapScanReader(path).report.lines() == ["no chunk index: the file was read linearly"]


@pytest.mark.parametrize("opcode", [0x07, 0x02, 0x0E, 0x86])
@pytest.mark.parametrize("crcs", [True, False])
def test_a_chunk_whose_opcode_is_damaged_is_read_as_the_chunk_it_is(tmp_path, opcode, crcs):
    """In a file without index, a chunk whose opcode was flipped into a message index, a
    footer, a summary offset or a private record (each of them a record the walk passes over
    or stops at) is still read, as its data is an intact chunk; the report says so."""
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(
        path, n_scans=N_SCANS, n_points=200, chunk_size=3_000, indexed=False, crcs=crcs
    )
    chunk = regions_of(path, "chunk")[2]
    data = bytearray(path.read_bytes())
    data[chunk.start] = opcode
    path.write_bytes(bytes(data))
    reader = McapScanReader(path)
    items = list(reader)
    assert check_scans_against_truth(items, truth) == list(range(N_SCANS))
    assert f"byte {chunk.start}: the record there has opcode {opcode:#x}, but holds an intact " in (
        "\n".join(reader.report.lines())
    )


def test_a_chunk_whose_opcode_is_damaged_after_a_bad_chunk_keeps_the_numbers(tmp_path):
    """A bad chunk, then a chunk whose opcode was flipped into a message index: the bad
    chunk's loss is counted by its own message index records, not by the next chunk's too, so
    every scan keeps its number."""
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=200, chunk_size=3_000)
    bad, disguised = regions_of(path, "chunk")[1:3]
    data = bytearray(path.read_bytes())
    data[bad.end - 30] ^= 0xFF
    data[disguised.start] = 0x07
    path.write_bytes(bytes(data))
    items = list(McapScanReader(path))
    assert [(i.index, type(i).__name__) for i in items] == [(0, "Scan"), (1, "SkippedScan")] + [
        (k, "Scan") for k in range(2, N_SCANS)
    ]
    assert check_scans_against_truth(items, truth) == [0, 2, 3, 4, 5]


@pytest.mark.parametrize("edit", ["opcode", "channel id"])
def test_a_bad_chunk_whose_cloud_is_no_longer_one_marks_the_scans_after_it(tmp_path, edit):
    """A damaged chunk whose records still parse whole, but whose cloud's record is no record
    a chunk holds (what a flipped bit in compressed data does to every copy of an opcode), or
    is a message on the /tf channel (a flipped bit in its channel id): its count is unknown,
    or counted from the damaged bytes, and either way the scans after it are marked, as their
    numbers may differ from the intact file's."""
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(
        path, n_scans=N_SCANS, n_points=200, chunk_size=3_000, indexed=False, compression="none"
    )
    chunk = regions_of(path, "chunk")[2]
    data = bytearray(path.read_bytes())
    at, size = chunk.fields["compression"]
    pos = at + size + 8  # the chunk's records
    while data[pos] != 0x05 or struct.unpack_from("<H", data, pos + 9)[0] != 3:  # its cloud
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    if edit == "opcode":
        data[pos] = 0x88  # an opcode no chunk holds
    else:
        struct.pack_into("<H", data, pos + 9, 2)  # /tf's channel
    path.write_bytes(bytes(data))
    reader = McapScanReader(path)
    items = list(reader)
    (loss,) = [x for x in reader.report.losses if "chunk skipped" in x.what]
    assert loss.uncounted == (edit == "opcode")
    scans = [i for i in items if not isinstance(i, SkippedScan)]
    assert [s.index for s in scans] == [0, 1, 2, 3, 4]  # the cloud after it took number 2
    assert sorted(reader.report.suspect) == [2, 3, 4]
    assert check_scans_against_truth(scans[:2], truth) == [0, 1]


@pytest.mark.parametrize("compression,counted", [("none", True), ("zstd", False)])
def test_a_bad_chunk_in_a_file_without_index_is_counted_or_said_unknown(
    tmp_path, compression, counted
):
    """Without message index records, an uncompressed damaged chunk still shows its records,
    which number the scans after it as in the intact file (marked all the same: a flipped
    channel id would have put a cloud on another topic); a compressed one cannot be counted:
    the loss says so. Either way the scans after it are marked (their numbers may differ from
    those in the intact file)."""
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(
        path,
        n_scans=N_SCANS,
        n_points=200,
        chunk_size=3_000,
        indexed=False,
        compression=compression,
    )
    chunks = regions_of(path, "chunk")
    flip(path, chunks[2].end - 60)
    reader = McapScanReader(path)
    items = list(reader)
    (loss,) = [x for x in reader.report.losses if "chunk skipped" in x.what]
    if counted:
        assert "(counted from its damaged records)" in loss.what and loss.messages > 0
        assert [i.index for i in items] == list(range(N_SCANS))
        skipped = [i.index for i in items if isinstance(i, SkippedScan)]
        assert check_scans_against_truth(items, truth) == sorted(set(range(N_SCANS)) - set(skipped))
        first_after = max(skipped) + 1
        assert sorted(reader.report.suspect) == list(range(first_after, N_SCANS))
        assert (
            "whose messages were counted from its damaged bytes, came before it"
            in (reader.report.suspect[first_after])
        )
    else:
        assert loss.uncounted and loss.line().endswith(": an unknown number of messages lost")
        scans = [i for i in items if not isinstance(i, SkippedScan)]
        first_after = min(reader.report.suspect)
        assert sorted(reader.report.suspect) == [s.index for s in scans if s.index >= first_after]
        assert reader.report.suspect[first_after].endswith(
            "holding an unknown number of messages, came before it, so its number may differ "
            "from the intact file's"
        )
        check_scans_against_truth([s for s in scans if s.index < first_after], truth)


def test_an_attachment_with_a_bad_crc_is_reported(tmp_path):
    from mcap.writer import Writer

    path = tmp_path / "log.mcap"
    write_synthetic_log(path, n_scans=2, n_points=50, chunked=False, compression="none")
    with open(tmp_path / "att.mcap", "wb") as f:
        w = Writer(f)
        w.start()
        w.add_attachment(
            create_time=1,
            log_time=1,
            name="calib.yaml",
            media_type="text/yaml",
            data=b"k: 1\n" * 20,
        )
        w.finish()
    (att,) = regions_of(tmp_path / "att.mcap", "attachment")
    record = bytearray((tmp_path / "att.mcap").read_bytes()[att.start : att.end])
    record[-10] ^= 0xFF  # its data, not its CRC
    data = bytearray(path.read_bytes())
    header = regions_of(path, "header")[0]
    data[header.end : header.end] = record  # right after the header record
    path.write_bytes(bytes(data))
    reader = McapScanReader(path)
    assert len([s for s in reader if not isinstance(s, SkippedScan)]) == 2
    assert (
        f"attachment at byte {header.end}: 'calib.yaml': its CRC does not match (tisem "
        "does not use attachments)" in reader.report.lines()
    )


def test_scans_posed_across_lost_tf_messages_are_marked(tmp_path):
    """A lost chunk also held /tf samples: a scan whose pose is interpolated across the gap
    gets another pose than from the intact file, so it is marked; the others are identical."""
    from tisem.testing.oracle import signature

    path = tmp_path / "log.mcap"
    # /tf at 20 Hz: the sample after scan 2's stamp is logged after its cloud, in the next chunk
    write_synthetic_log(path, n_scans=N_SCANS, n_points=200, chunk_size=3_000, tf_rate_hz=20)
    intact = {s.index: signature(s) for s in McapScanReader(path)}
    chunks = regions_of(path, "chunk")
    flip(path, chunks[3].end - 60)
    reader = McapScanReader(path)
    items = [s for s in reader if not isinstance(s, SkippedScan)]
    suspect = reader.report.suspect
    assert sorted(suspect) == [2] and all(
        why.startswith(
            "pose messages were lost and its pose is "
            "interpolated across the gap: edge map -> base_link "
            "has no samples from"
        )
        for why in suspect.values()
    )
    assert all(signature(s) == intact[s.index] for s in items if s.index not in suspect)


def test_scans_stamped_as_their_tf_samples_are_not_marked_for_a_lost_one(tmp_path):
    """`kitti-to-mcap` stamps /tf with the clouds' stamps: a scan's pose is then a sample, not
    an interpolation, and a /tf message lost beside it changes nothing. Only the lost scan
    goes; the scans on either side of it, the last included, are read as intact."""
    from test_mcap_kitti import write_tiny_sequence

    from tisem.io.kitti_mcap import write_kitti_mcap
    from tisem.testing.oracle import signature

    folder = write_tiny_sequence(tmp_path / "seq", n_scans=4, n_points=45_000)
    path = tmp_path / "log.mcap"
    write_kitti_mcap(folder, path)  # (clouds over 1 MiB: a chunk per scan and its /tf)
    intact = {s.index: signature(s) for s in McapScanReader(path)}
    chunks = regions_of(path, "chunk")
    assert len(chunks) == 4
    flip(path, (chunks[2].start + chunks[2].end) // 2)  # scan 2's chunk, the /tf at its stamp
    reader = McapScanReader(path)
    items = [s for s in reader if not isinstance(s, SkippedScan)]
    assert [s.index for s in items] == [0, 1, 3]
    assert reader.report.suspect == {}
    assert all(signature(s) == intact[s.index] for s in items)


def chunk_records(data: bytes, chunk) -> list[tuple[int, int, bytes]]:
    """(opcode, offset in the file, content) of the records of an uncompressed chunk."""
    at, size = chunk.fields["data length"]
    pos = at + size
    end = pos + struct.unpack_from("<Q", data, at)[0]
    out = []
    while pos < end:
        opcode, length = struct.unpack_from("<BQ", data, pos)
        out.append((opcode, pos, data[pos + 9 : pos + 9 + length]))
        pos += 9 + length
    return out


def test_lost_tf_messages_counted_on_an_unknown_channel_still_mark_the_scans(tmp_path):
    """A file without a summary is read linearly, and a chunk whose CRC fails is counted from
    its own records. Here every /tf message of one chunk has a damaged channel id, so the loss
    counts them on a channel no record names: the scans posed across that gap are marked all
    the same; those after it are marked too, as the lost messages might have been clouds (their
    numbers may differ from the intact file's); the others are identical."""
    from tisem.testing.oracle import signature

    path = tmp_path / "log.mcap"
    write_synthetic_log(
        path,
        n_scans=5,
        n_points=40,
        chunk_size=1500,
        tf_rate_hz=20,
        compression="none",
        indexed=False,
        seed=7,
    )
    intact = {s.index: signature(s) for s in McapScanReader(path)}
    data = bytearray(path.read_bytes())
    chunks = regions_of(path, "chunk")
    tf_id = next(
        struct.unpack_from("<H", content)[0]
        for opcode, _, content in chunk_records(data, chunks[0])
        if opcode == 0x04 and b"/tf\x03" in content  # a Channel record, topic "/tf"
    )
    damaged = 0
    for opcode, pos, content in chunk_records(data, chunks[2]):
        if opcode == 0x05 and struct.unpack_from("<H", content)[0] == tf_id:
            struct.pack_into("<H", data, pos + 9, 7)
            damaged += 1
    assert damaged >= 2 and tf_id != 7
    path.write_bytes(bytes(data))
    reader = McapScanReader(path)
    items = [s for s in reader if not isinstance(s, SkippedScan)]
    assert any(f"{damaged} on channel 7" in line for line in reader.report.lines())
    suspect = reader.report.suspect
    posed = [k for k, why in suspect.items() if why.startswith("pose messages were lost")]
    assert posed, "the scene needs a scan posed across the lost /tf messages"
    assert all(
        k in posed or why.endswith("so its number may differ from the intact file's")
        for k, why in suspect.items()
    )
    assert all(signature(s) == intact[s.index] for s in items if s.index not in suspect)


@pytest.mark.parametrize("form", ["file", "file without summary", "rosbag2 folder"])
def test_a_cloud_outside_any_crc_whose_channel_id_is_damaged_marks_the_scans_after_it(
    tmp_path, form
):
    """A message outside chunks whose channel id no Channel record names cannot be decoded. No
    CRC covers it, so it may have been a cloud whose id the damage changed: the scans after it
    are mapped and marked (their numbers may differ from the intact file's), the loss is
    reported as such, and the scans before it are untouched. The same in a rosbag2 folder,
    whose files number their channels their own way."""
    from tisem.io.bag_open import open_scan_reader

    folder = tmp_path / "bag"
    folder.mkdir()
    path = folder / "bag_0.mcap"
    truth = write_synthetic_log(
        path, n_scans=N_SCANS, n_points=200, chunked=False, compression="none"
    )
    clouds = [r for r in regions_of(path, "message") if r.end - r.start > 2000]
    data = bytearray(path.read_bytes())
    struct.pack_into("<H", data, clouds[2].start + 9, 77)  # the channel id of cloud 2
    if form == "file without summary":  # read linearly, as a file cut after its data
        data = data[: regions_of(path, "data end")[0].end]
    path.write_bytes(bytes(data))
    reader = open_scan_reader(folder if form == "rosbag2 folder" else path)
    items = list(reader)
    assert check_scans_against_truth(items[:2], truth) == [0, 1]
    assert [type(i).__name__ for i in items] == ["Scan"] * (N_SCANS - 1)
    assert sorted(reader.report.suspect) == list(range(2, N_SCANS - 1))
    where = "bag_0.mcap: " if form == "rosbag2 folder" else ""
    assert set(reader.report.suspect.values()) == {
        f"{where}message at log time 100.248 s, a loss on a channel no record names (clouds, "
        "maybe), came before it, so its number may differ from the intact file's"
    }
    (line,) = [line for line in reader.report.lines() if "channel 77" in line]
    assert "no Channel record names its id" in line and "1 message" in line


def test_a_damaged_id_that_names_a_later_channel_neither_counts_nor_renumbers_a_scan(tmp_path):
    """Read linearly, a message can carry the id of a channel whose record comes later: here the
    first /tf message, damaged into the clouds' id before their Channel record. It is no cloud
    the scans' pass can number, so the scan count leaves it out (it was one too many), and, as
    no CRC vouches for it, the scans after it are marked."""
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(
        path, n_scans=N_SCANS, n_points=200, chunked=False, compression="none"
    )
    with open(path, "rb") as f:
        channels = make_reader(f).get_summary().channels.values()
    ids = {c.topic: c.id for c in channels}
    data = bytearray(path.read_bytes())
    first_tf = next(
        r
        for r in regions_of(path, "message")
        if struct.unpack_from("<H", data, r.start + 9)[0] == ids["/tf"]
    )
    struct.pack_into("<H", data, first_tf.start + 9, ids["/velodyne_points"])
    path.write_bytes(bytes(data[: regions_of(path, "data end")[0].end]))
    reader = McapScanReader(path)
    items = list(reader)
    assert len(reader) == len(items) == N_SCANS
    # (scan 0 lies before the second /tf sample: without the first it has no pose)
    assert isinstance(items[0], SkippedScan) and "cannot look up" in items[0].reason
    assert check_scans_against_truth(items, truth) == list(range(1, N_SCANS))
    assert sorted(reader.report.suspect) == list(range(1, N_SCANS))


def test_a_message_index_whose_opcode_turned_message_is_not_taken_for_a_cloud(tmp_path):
    """0x07 -> 0x05 is one bit: the chunk index says a message index record starts there."""
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=200, chunk_size=3_000)
    index = regions_of(path, "message index")[2]
    data = bytearray(path.read_bytes())
    data[index.start] = 0x05
    path.write_bytes(bytes(data))
    reader = McapScanReader(path)
    assert check_scans_against_truth(list(reader), truth) == list(range(N_SCANS))
    assert reader.report.lines()[0] == (
        f"byte {index.start}: the chunk index has a message index "
        f"record here, the data opcode 0x5: taken as a damaged "
        f"message index record"
    )


def test_more_messages_than_the_summary_counts_marks_the_scans_from_there(tmp_path):
    """A cloud record outside the chunks that the summary does not count: damage taken for a
    message, so its scan (and any after it) is marked."""
    path, loose = tmp_path / "log.mcap", tmp_path / "unchunked.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=200, chunk_size=3_000)
    write_synthetic_log(loose, n_scans=N_SCANS, n_points=200, chunked=False)
    extra = [r for r in regions_of(loose, "message") if r.end - r.start > 2000][1]
    record = loose.read_bytes()[extra.start : extra.end]
    data = bytearray(path.read_bytes())
    (data_end,) = regions_of(path, "data end")
    data[data_end.start : data_end.start] = record
    footer = len(data) - 37
    for at in (footer + 9, footer + 17):  # summary start, summary offsets
        struct.pack_into("<Q", data, at, struct.unpack_from("<Q", data, at)[0] + len(record))
    path.write_bytes(bytes(data))
    refresh_summary_crc(path)
    reader = McapScanReader(path)
    items = list(reader)
    assert check_scans_against_truth(items[:N_SCANS], truth) == list(range(N_SCANS))
    assert [i.index for i in items] == list(range(N_SCANS + 1))
    assert list(reader.report.suspect) == [N_SCANS]
    assert any(
        "the data holds more messages than the summary counts (1 on /velodyne_points)" in line
        for line in reader.report.lines()
    )


def test_the_data_crc_is_checked_even_when_the_walk_never_reaches_the_data_end(tmp_path):
    """Zeros over the end of the last message and the header after it: the walk stops there,
    yet the footer leads to the data-end record, whose CRC says the data is corrupted."""
    path = tmp_path / "log.mcap"
    write_synthetic_log(
        path, n_scans=4, n_points=200, chunked=False, compression="none", data_crc=True
    )
    last = regions_of(path, "message")[-1]
    data = bytearray(path.read_bytes())
    data[last.start - 8 : last.start + 2] = bytes(10)
    path.write_bytes(bytes(data))
    reader = McapScanReader(path)
    scans = [s for s in reader if not isinstance(s, SkippedScan)]
    lines = reader.report.lines()
    assert lines[0].startswith(f"bytes {last.start}-") and "invalid record opcode 0x0" in lines[0]
    assert any(
        line.startswith("data section: its CRC (in the data-end record) does not match")
        for line in lines
    )
    assert sorted(reader.report.suspect) == [s.index for s in scans]


def _copy_messages(src, dst, topics: list[str], keep, extra=(), zstd_messages=False) -> None:
    """The messages of `src` that `keep(topic, log time)` keeps, in a new file `dst` whose
    channels are registered in the order of `topics` (so that its channel ids are its own),
    and the `extra` messages, (topic, log time, data) each. Its chunks are zstd-compressed,
    or (`zstd_messages`, as rosbag2's per-message compression writes) each message is."""
    import zstandard
    from mcap.writer import CompressionType, Writer

    with open(src, "rb") as f:
        messages = list(make_reader(f).iter_messages())
    with open(dst, "wb") as out:
        chunks = CompressionType.NONE if zstd_messages else CompressionType.ZSTD
        w = Writer(out, chunk_size=8_000, compression=chunks)
        w.start(profile="ros2", library="test")
        ids, schema_ids = {}, {}
        for topic in topics:
            schema, channel, _ = next(m for m in messages if m[1].topic == topic)
            if schema.name not in schema_ids:
                schema_ids[schema.name] = w.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            ids[topic] = w.register_channel(topic, "cdr", schema_ids[schema.name])
        kept = [
            (m.log_time, channel.topic, m.data)
            for _schema, channel, m in messages
            if channel.topic in ids and keep(channel.topic, m.log_time)
        ]
        for log_time, topic, data in sorted([*kept, *((t, c, d) for c, t, d in extra)]):
            if zstd_messages:
                data = zstandard.ZstdCompressor().compress(data)
            w.add_message(ids[topic], log_time, data, log_time)
        w.finish()


def flip_first_chunk(path) -> None:
    """A byte flipped near the end of the file's first chunk (inside its last message)."""
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    first = min(chunks, key=lambda c: c.chunk_start_offset)
    flip(path, first.chunk_start_offset + first.chunk_length - 100)


@pytest.mark.parametrize("compression", ["chunks", "messages", "messages, no metadata"])
def test_a_damaged_mount_from_a_split_file_that_numbers_its_channels_its_own_way(
    tmp_path, compression
):
    """A rosbag2 folder of two MCAP files: the first holds no /tf_static, the second's first
    chunk holds it and is damaged. There /tf_static is the file's channel 1, the id the
    recording gave its clouds: the salvaged mount is decoded as a transform all the same, and
    every scan is marked. With rosbag2's per-message compression the salvaged message is
    inflated first, as the folder's metadata says, or (without it) as its bytes say."""
    from tisem.io.bag_open import open_scan_reader

    whole = tmp_path / "whole.mcap"
    truth = write_synthetic_log(whole, n_scans=N_SCANS, n_points=12_000, compression="zstd")
    folder = tmp_path / "bag"
    folder.mkdir()
    per_message = compression != "chunks"
    if compression == "messages":
        (folder / "metadata.yaml").write_text(per_message_metadata(["bag_0.mcap", "bag_1.mcap"]))
    split_ns = truth["stamps_ns"][3]  # scans 0-2 in the first file, 3-5 in the second
    _copy_messages(
        whole,
        folder / "bag_0.mcap",
        ["/velodyne_points", "/tf"],
        lambda _, t: t < split_ns,
        zstd_messages=per_message,
    )
    second = folder / "bag_1.mcap"
    _copy_messages(
        whole,
        second,
        ["/tf_static", "/velodyne_points", "/tf"],
        lambda topic, t: topic == "/tf_static" or t >= split_ns,
        zstd_messages=per_message,
    )
    flip_first_chunk(second)
    reader = open_scan_reader(folder)
    items = list(reader)
    assert isinstance(items[3], SkippedScan)
    assert check_scans_against_truth(items, truth) == [0, 1, 2, 4, 5]
    assert sorted(reader.report.suspect) == [0, 1, 2, 4, 5]
    assert "from the bag_1.mcap: chunk at byte" in reader.report.suspect[0]


def test_the_tf_notes_of_a_mount_read_from_damage_are_given_once(tmp_path):
    """The transforms are built again when the mount comes from a damaged chunk: what the
    first build noted (here an ignored transform) is noted once, not once per build."""
    from tisem.io.mcap_writer import Ros2McapWriter

    whole = tmp_path / "whole.mcap"
    truth = write_synthetic_log(whole, n_scans=N_SCANS, n_points=12_000, compression="zstd")
    odd = tmp_path / "odd.mcap"  # one /tf message whose translation is not finite
    T = np.eye(4)
    T[0, 3] = np.nan
    with Ros2McapWriter(odd) as w:
        w.write_transforms([("map", "odd", truth["stamps_ns"][2], T)], truth["stamps_ns"][2])
    with open(odd, "rb") as f:
        ((_, _, nan_tf),) = list(make_reader(f).iter_messages())
    path = tmp_path / "log.mcap"
    topics = ["/tf_static", "/tf", "/velodyne_points"]
    _copy_messages(whole, path, topics, lambda *_: True, [("/tf", nan_tf.log_time, nan_tf.data)])
    flip_first_chunk(path)
    reader = McapScanReader(path)
    items = list(reader)
    assert check_scans_against_truth(items, truth) == list(range(1, N_SCANS))
    assert sorted(reader.report.suspect) == list(range(1, N_SCANS))
    note = "tf: ignored 1 transform(s) map -> odd with non-finite values"
    assert reader.report.notes.count(note) == 1


def test_the_fuzz_campaigns_per_message_recording_reads_as_its_plain_twin(tmp_path):
    """The fuzz's rosbag2 split compressed message by message (its folder's metadata says so)
    gives the scans of the same recording written plain: the base its damaged copies are
    judged against is the recording, not an empty one."""
    from tisem.io.bag_open import open_scan_reader
    from tisem.testing.mcap_damage import ZSTD_MESSAGES_FOLDER, write_bases
    from tisem.testing.oracle import reference

    bases = write_bases(tmp_path)
    plain = reference(open_scan_reader(bases["uncompressed"].path))
    for name in ("zstd messages", "zstd messages unchunked"):
        per_message = bases[name]
        assert per_message.path.parent.name == ZSTD_MESSAGES_FOLDER
        assert per_message.data.count(b"\x28\xb5\x2f\xfd") >= 5, "each message a zstd frame"
        got = reference(open_scan_reader(per_message.path))
        assert sorted(got) == sorted(plain) and len(got) == 5, name
        for k, scan in got.items():
            np.testing.assert_array_equal(scan.points_sensor, plain[k].points_sensor)
            np.testing.assert_array_equal(scan.labels, plain[k].labels)
            np.testing.assert_array_equal(scan.T_world_sensor, plain[k].T_world_sensor)
