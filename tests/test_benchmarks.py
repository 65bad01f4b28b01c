"""The mapping benchmarks run with tiny arguments (so they never rot); no timing is checked.

Each maps a four-scan synthetic sequence written by apps/make_synthetic.py (the benchmarks start
their own Taichi runtimes, one map each)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import free_space, kernel_length, modes, peers, throughput
from tisem.mapper import STAGES

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bench") / "street"
    subprocess.run(
        [
            sys.executable,
            str(REPO / "apps" / "make_synthetic.py"),
            "--out",
            str(out),
            "--scans",
            "4",
            "--points-per-ring",
            "128",
            "--no-progress",
        ],
        check=True,
        capture_output=True,
    )
    return out


@pytest.mark.slow
def test_throughput_benchmark_runs(tiny_sequence, tmp_path, capsys):
    out = tmp_path / "t.json"
    assert (
        throughput.main(
            [
                "--data",
                str(tiny_sequence),
                "--scans",
                "3",
                "--reference-scans",
                "1",
                "--fresh-maps",
                "2",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    r = json.loads(out.read_text())
    assert set(r["stages"]) == {*STAGES, "query"}
    assert r["scans"] == 3 and r["seconds_per_scan"] > 0 and r["active_voxels"] > 0
    assert r["arch"] == "cpu" and r["threads"] == 2 and r["peak_rss_mb"] > 0
    assert r["minor_faults_per_scan"] >= 0
    assert r["speedup_vs_numpy"] == pytest.approx(
        r["reference_seconds_per_scan"] / r["seconds_per_scan"]
    )
    # two fresh maps of the street's 4 scans: the 3 after each map's first are timed
    fresh = r["fresh_map"]
    assert fresh["rounds"] == 2 and fresh["distinct_scans"] == 4 and fresh["scans"] == 6
    assert set(fresh["stages"]) == set(STAGES) and fresh["seconds_per_scan"] > 0
    assert fresh["minor_faults_per_scan"] >= 0
    out_text = capsys.readouterr().out
    assert out_text.count("| **mapping, end to end** |") == 2 and "fresh maps (2 rounds" in out_text


def test_throughput_refuses_a_negative_number_of_fresh_maps(capsys):
    with pytest.raises(SystemExit):
        throughput.parse_args(["--fresh-maps", "-1"])
    assert "--fresh-maps -1: expected a whole number >= 0" in capsys.readouterr().err


@pytest.mark.slow
def test_free_space_benchmark_runs(tiny_sequence, tmp_path, capsys):
    out = tmp_path / "f.json"
    args = ["--data", str(tiny_sequence), "--scans", "3", "--json", str(out)]
    assert free_space.main(args) == 0
    r = json.loads(out.read_text())
    assert set(r["kernels_ms"]) == set(free_space.KERNELS)
    assert r["kernels_ms"]["cast_free"] > 0 and r["threads"] == 2
    n = r["per_scan"]
    assert n["rays"] > 0 and n["steps"] >= n["steps_live_blocks"] >= n["steps_live_voxels"]
    assert 0 < n["memory_writes"] <= n["steps"] - n["steps_live_voxels"]
    assert "| cast_free |" in capsys.readouterr().out


@pytest.mark.slow
def test_kernel_length_benchmark_runs(tiny_sequence, tmp_path, capsys):
    out = tmp_path / "k.json"
    assert (
        kernel_length.main(
            [
                "--data",
                str(tiny_sequence),
                "--synthetic-scans",
                "0",
                "--repeats",
                "2",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    rows = json.loads(out.read_text())["rows"]
    assert [r["kernel"] for r in rows] == [
        "fixed 1 vox",
        "fixed 2 vox",
        "fixed 4 vox",
        "fixed 6 vox",
        "adaptive",
        "adaptive + decay (st)",
    ]
    for r in rows:
        assert r["rounds"] == 2 and r["seconds_per_scan"] > 0
        assert 0.5 < r["accuracy"] <= 1 and 0 < r["miou"] <= r["accuracy"] + 0.5
    assert "| fixed 6 vox | 1.2 m |" in capsys.readouterr().out


@pytest.mark.slow
def test_modes_benchmark_runs(tiny_sequence, tmp_path, capsys):
    out = tmp_path / "m.json"
    assert (
        modes.main(
            [
                "--data",
                str(tiny_sequence),
                "--modes",
                "csm",
                "st",
                "--out",
                str(tmp_path / "runs"),
                "--json",
                str(out),
            ]
        )
        == 0
    )
    rows = json.loads(out.read_text())["rows"]
    assert [r["row"] for r in rows][-2:] == ["csm", "st"]
    assert all(0.5 < r["accuracy"] <= 1 for r in rows)
    assert "| st |" in capsys.readouterr().out


@pytest.mark.slow
def test_peers_benchmark_runs_tisem(tiny_sequence, tmp_path, capsys):
    """tisem's rows on two held-out splits, each mapped alone; S-BKI's need its driver."""
    out = tmp_path / "p.json"
    assert (
        peers.main(
            [
                "--data",
                str(tiny_sequence),
                "--splits",
                "0-1",
                "2-3",
                "--methods",
                "st",
                "bki4",
                "--rounds",
                "1",
                "--out",
                str(tmp_path / "runs"),
                "--json",
                str(out),
            ]
        )
        == 0
    )
    rows = json.loads(out.read_text())["rows"]
    assert [(r["split"], r["method"]) for r in rows] == [
        (s, m) for s in ("0-1", "2-3") for m in ("network input", "st", "bki4")
    ]
    for r in rows:
        assert 0.5 < r["accuracy"] <= 1 and r["per_class_iou"] and r["present_classes"]
        assert r["method"] == "network input" or r["seconds_per_scan"] > 0
    assert "| 2-3 | st |" in capsys.readouterr().out


@pytest.mark.slow
def test_peers_benchmark_runs_sbki(tiny_sequence, tmp_path, capsys):
    if not peers.SBKI_BIN.is_file():
        pytest.skip(f"S-BKI is not built ({peers.SBKI_BIN}): bash ../shared/peers/sbki/build.sh")
    out = tmp_path / "p.json"
    assert (
        peers.main(
            [
                "--data",
                str(tiny_sequence),
                "--splits",
                "0-3",
                "--methods",
                "csm",
                "sbki-upstream",
                "--rounds",
                "1",
                "--out",
                str(tmp_path / "runs"),
                "--json",
                str(out),
            ]
        )
        == 0
    )
    rows = {r["method"]: r for r in json.loads(out.read_text())["rows"]}
    assert rows["sbki-upstream"]["seconds_per_scan"] > 0
    assert 0.5 < rows["sbki-upstream"]["accuracy"] <= 1
    assert "| 0-3 | sbki-upstream |" in capsys.readouterr().out


FAKE_SBKI = """#!{python}
# S-BKI's driver as peers.py calls it, answering every point with its ground truth
import shutil, sys
from pathlib import Path
a = dict(zip(sys.argv[1::2], sys.argv[2::2]))
out = Path(a["--out"]) / "sequences" / "00" / "predictions"
out.mkdir(parents=True)
for i in range(int(a["--first"]), int(a["--last"]) + 1):
    shutil.copy(Path(a["--data"]) / "labels" / f"{{i:06d}}.label", out)
print("sbki_s_per_scan=0.25")
"""


@pytest.mark.slow
def test_peers_benchmark_scores_only_this_runs_peer_predictions(tiny_sequence, tmp_path, capsys):
    """S-BKI alone (no tisem method: the device line still needs a Taichi runtime), in an out
    folder where an earlier run on other data left predictions under another sequence name:
    they are removed, and the driver's own predictions (here the ground truth) are scored."""
    driver = tmp_path / "sbki_kitti"
    driver.write_text(FAKE_SBKI.format(python=sys.executable))
    driver.chmod(0o755)
    stale = tmp_path / "runs" / "0-3" / "sbki-upstream" / "sequences" / "07" / "predictions"
    stale.mkdir(parents=True)
    for i in range(4):
        np.zeros(7, "<u4").tofile(stale / f"{i:06d}.label")
    out = tmp_path / "p.json"
    args = ["--data", str(tiny_sequence), "--splits", "0-3", "--methods", "sbki-upstream"]
    args += ["--sbki-bin", str(driver), "--out", str(tmp_path / "runs"), "--json", str(out)]
    assert peers.main([*args, "--rounds", "1"]) == 0
    assert not stale.exists()
    (row,) = json.loads(out.read_text())["rows"]
    assert (row["method"], row["accuracy"], row["miou"]) == ("sbki-upstream", 1.0, 1.0)
    assert row["seconds_per_scan"] == 0.25
    assert "| 0-3 | sbki-upstream | 1.0000 | 1.0000 | 0.250 |" in capsys.readouterr().out


@pytest.mark.slow
def test_peers_benchmark_skips_an_unbuilt_peer(tiny_sequence, tmp_path, capsys):
    out = tmp_path / "p.json"
    assert (
        peers.main(
            [
                "--data",
                str(tiny_sequence),
                "--splits",
                "0-3",
                "--methods",
                "csm",
                "sbki-tuned",
                "--rounds",
                "1",
                "--sbki-bin",
                str(tmp_path / "none"),
                "--out",
                str(tmp_path / "runs"),
                "--json",
                str(out),
            ]
        )
        == 0
    )
    r = json.loads(out.read_text())
    assert [x["method"] for x in r["rows"]] == ["network input", "csm"]
    assert "sbki-tuned" in r["skipped"]
    assert "skipped sbki-tuned: S-BKI is not built" in capsys.readouterr().out


@pytest.mark.parametrize(
    "script",
    sorted(
        p.name
        for p in (REPO / "benchmarks").glob("*.py")
        if p.name not in ("__init__.py", "common.py")
    ),
)
def test_every_benchmark_starts_as_a_script(script):
    """`python benchmarks/NAME.py`, as the docs run them, from outside the checkout."""
    proc = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / script), "--help"],
        capture_output=True,
        text=True,
        cwd="/",
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-500:]
    assert "usage:" in proc.stdout
