"""Damaged recordings: cut short, bad chunks, no index, no CRC, undecodable messages.

Each test writes a small log, damages its bytes, and checks that every intact message is
recovered, the damaged part is reported (never a traceback), and no scan carries wrong data.
"""
from __future__ import annotations

import struct

import numpy as np
import pytest
from mcap.reader import make_reader

from tisem.errors import DatasetError, SkippedScan
from tisem.io.mcap_reader import McapOptions, McapScanReader
from tisem.labels import raw_to_train
from tisem.scan import Scan
from tisem.synth.mcap_log import write_synthetic_log

N_SCANS = 6


def top_level_records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of each record after the magic, up to the data end."""
    out, pos = [], 8
    while pos < len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        out.append((opcode, pos, pos + 9 + length))
        if opcode == 0x0F:             # data end: the summary follows
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
    truth = write_synthetic_log(full, n_scans=N_SCANS, n_points=300, chunked=False,
                                compression="none")
    data = full.read_bytes()
    size = int(len(data) * fraction)
    messages = [r for r in top_level_records(data) if r[0] == 0x05]
    complete = [r for r in messages if r[2] <= size]
    clouds = [r for r in complete if len(data[r[1]:r[2]]) > 2000]      # clouds are the big ones
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
    truth = write_synthetic_log(full, n_scans=N_SCANS, n_points=600, compression=compression,
                                chunk_size=8_000)                  # about one chunk per scan
    with open(full, "rb") as f:
        summary = make_reader(f).get_summary()
    size = int(full.stat().st_size * fraction)
    whole_chunks = [c for c in summary.chunk_indexes
                    if c.chunk_start_offset + c.chunk_length <= size]
    clouds_in_whole_chunks = sum(any(c.message_start_time <= t + 35_000_000 <= c.message_end_time
                                     for c in whole_chunks) for t in truth["stamps_ns"])
    cut(full, tmp_path / "cut.mcap", size)

    reader = McapScanReader(tmp_path / "cut.mcap")
    items = list(reader)
    got = check_scans_against_truth(items, truth)
    assert got == list(range(len(got))) and len(got) >= clouds_in_whole_chunks
    if fraction > 0.99:   # only the summary is gone: nothing lost
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
    with pytest.raises(DatasetError,
                       match="no point-cloud messages found.*the file is damaged.*cut"):
        McapScanReader(tmp_path / "cut.mcap")


@pytest.mark.parametrize("content,message", [
    (b"", "the file is empty"), (b"PK\x03\x04 not an mcap at all", "not an MCAP file"),
])
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
    (chunk,) = [c for c in summary.chunk_indexes
                if c.message_start_time <= log_time <= c.message_end_time]
    return chunk


def flip(path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x5A
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
@pytest.mark.parametrize("summary", ["intact", "cut off"])
def test_a_chunk_with_a_bad_crc_is_skipped_and_reported(tmp_path, compression, summary):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=600, compression=compression,
                                chunk_size=8_000)
    chunk = chunk_of_scan(path, truth, 2)
    flip(path, chunk.chunk_start_offset + chunk.chunk_length - 100)   # inside its data
    if summary == "cut off":   # linear reading; the message index records still count the loss
        data = path.read_bytes()
        end = [r for r in top_level_records(data) if r[0] == 0x0F][0][1]
        path.write_bytes(data[:end])
    reader = McapScanReader(path)
    items = list(reader)
    assert [i.index for i in items] == list(range(N_SCANS))       # numbering as in the intact file
    assert check_scans_against_truth(items, truth) == [0, 1, 3, 4, 5]
    assert isinstance(items[2], SkippedScan)
    assert f"chunk at byte {chunk.chunk_start_offset}" in items[2].reason
    (loss,) = reader.report.losses if summary == "intact" else reader.report.losses[:1]
    assert loss.topics["/velodyne_points"] == 1 and "chunk skipped" in loss.what
    assert "1 on /velodyne_points" in loss.line()


def test_a_damaged_chunk_header_loses_only_that_chunk(tmp_path):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=N_SCANS, n_points=600, chunk_size=8_000)
    chunk = chunk_of_scan(path, truth, 4)
    data = bytearray(path.read_bytes())
    data[chunk.chunk_start_offset + 1:chunk.chunk_start_offset + 9] = b"\xff" * 8   # its length
    path.write_bytes(bytes(data))
    reader = McapScanReader(path)
    items = list(reader)
    assert check_scans_against_truth(items, truth) == [0, 1, 2, 3, 5]
    assert "does not match the index" in reader.report.lines()[0]


@pytest.mark.parametrize("variant", [dict(indexed=False), dict(chunked=False),
                                     dict(indexed=False, chunked=False, compression="lz4")])
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
    frame = struct.pack("<I", 9) + b"velodyne\x00"               # a CDR string
    hits = [i for i in range(len(data)) if data.startswith(frame, i)]
    at = hits[3] + len(frame) + 3                                 # cloud 2 (after /tf_static)
    data[at:at + 16] = b"\xff" * 16                                # height, width, fields length
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
