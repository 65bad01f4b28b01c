"""The decode benchmark runs with tiny arguments (so it never rots); no timing is checked."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

spec = importlib.util.spec_from_file_location(
    "mcap_decode", Path(__file__).resolve().parents[1] / "benchmarks" / "mcap_decode.py"
)
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)


def test_benchmark_smoke(tmp_path, capsys):
    out = tmp_path / "decode.json"
    assert (
        bench.main(
            [
                "--scans",
                "2",
                "--points",
                "300",
                "--runs",
                "1",
                "--compression",
                "zstd",
                "none",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())
    assert [r["compression"] for r in result["rows"]] == ["zstd", "none"]
    assert all(r["points"] == 600 and r["points_per_s"] > 0 for r in result["rows"])
    assert "| zstd | 2 x 300 |" in capsys.readouterr().out
