"""The one line a run logs for a skipped scan (`SkippedScan.line`)."""

from __future__ import annotations

from test_semantickitti import make_sequence

from tisem.errors import SkippedScan
from tisem.io.semantickitti import SemanticKittiSequence


def test_a_skip_line_names_the_file_once(tmp_path):
    """The reader's reason starts with the scan's file; the line a run logs says it once."""
    d = make_sequence(tmp_path / "seq")
    bin_path = d / "velodyne" / "000001.bin"
    bin_path.write_bytes(bin_path.read_bytes()[:-3])
    (skipped,) = [s for s in SemanticKittiSequence(d) if hasattr(s, "reason")]
    line = skipped.line()
    assert line.startswith(f"skipped scan 1: {bin_path}: truncated scan file"), line
    assert line.count(str(bin_path)) == 1
    gate = SkippedScan(2, str(bin_path), "pose outlier: the sensor is 300 km away")
    assert gate.line() == f"skipped scan 2 ({bin_path}): pose outlier: the sensor is 300 km away"
