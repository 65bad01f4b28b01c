"""A bounded, seeded fuzz of the readers: a few hundred damaged MCAP recordings, ROS 1 bags and
SemanticKITTI folders, each read in a worker process (a signal is one failed case, not a dead
pytest). The promise: no signal, no exception but the project's own errors, and every scan a
reader yields is byte-identical to the intact input's or reported as damaged (see
`tisem.testing.oracle`). A failure names its seed, case and mutation; replay it with
`python benchmarks/fuzz_inputs.py --target T --seed S --case K --keep DIR`.
"""

from __future__ import annotations

import json

import pytest

from benchmarks import fuzz_inputs
from tisem.testing.fuzz import run_campaign, summary_table

SEED = 20240613
MCAP_CASES, KITTI_CASES, BAG_CASES = 300, 180, 300


def _failures(results) -> list[str]:
    return [r.line() for r in results if r.outcome == "failure"]


@pytest.mark.slow
def test_damaged_recordings_are_read_or_reported_never_silently_wrong():
    results = run_campaign("mcap", SEED, count=MCAP_CASES)
    assert len(results) == MCAP_CASES
    assert not _failures(results), summary_table(results)
    kinds = {r.outcome for r in results}
    assert {"identical", "reported", "refused"} <= kinds, summary_table(results)
    # (the rosbag2 split compressed message by message among them, read through its folder)
    per_message = {r.outcome for r in results if r.what.startswith("[zstd messages]")}
    assert {"identical", "reported"} <= per_message, per_message


@pytest.mark.slow
def test_damaged_kitti_folders_are_read_or_reported():
    results = run_campaign("kitti", SEED, count=KITTI_CASES)
    assert len(results) == KITTI_CASES
    assert not _failures(results), summary_table(results)
    kinds = {r.outcome for r in results}
    assert {"identical", "reported", "refused"} <= kinds, summary_table(results)


@pytest.mark.slow
def test_damaged_ros1_bags_are_read_or_reported_never_silently_wrong():
    pytest.importorskip("rosbags", reason="the rosbags package (tisem[mcap]) is not installed")
    results = run_campaign("rosbag", SEED, count=BAG_CASES)
    assert len(results) == BAG_CASES
    assert not _failures(results), summary_table(results)
    kinds = {r.outcome for r in results}
    assert {"identical", "reported", "refused"} <= kinds, summary_table(results)


def test_a_reader_process_that_dies_is_one_failed_case_and_the_campaign_goes_on():
    results = run_campaign("mcap", SEED, count=4, crash_case=1)
    assert [r.case for r in results] == [0, 1, 2, 3]
    assert results[1].outcome == "failure" and "died of SIGSEGV" in results[1].detail
    assert results[1].what.startswith("[") and f"seed {SEED} case 1" in results[1].line()
    assert all(r.outcome != "failure" for r in results[::2])


@pytest.mark.slow
def test_the_campaign_benchmark_runs_and_replays(tmp_path, capsys):
    out = tmp_path / "fuzz.json"
    assert fuzz_inputs.main(["--cases", "6", "--seed", "1", "--json", str(out)]) == 0
    results = json.loads(out.read_text())["results"]
    assert [r["target"] for r in results] == ["mcap"] * 6 + ["kitti"] * 6 + ["rosbag"] * 6
    assert not [r for r in results if r["outcome"] == "failure"], results
    printed = capsys.readouterr().out
    assert "| mcap | 6 |" in printed and "| kitti | 6 |" in printed and "| rosbag | 6 |" in printed
    assert (
        fuzz_inputs.main(
            ["--target", "mcap", "--seed", "1", "--case", "2", "--keep", str(tmp_path / "case")]
        )
        == 0
    )
    replayed = capsys.readouterr().out
    assert f"mcap seed 1 case 2: {results[2]['what'].split('] ', 1)[1]}" in replayed
    assert f"outcome: {results[2]['outcome']}" in replayed
    assert list((tmp_path / "case").glob("**/case2*"))  # (a per-message split: in its folder)
