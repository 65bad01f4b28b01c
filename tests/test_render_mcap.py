"""`tisem render` on a run of an MCAP recording draws what it draws for the same scans mapped
from their SemanticKITTI folder: same points, same accuracies per panel."""

from __future__ import annotations

import pytest

pytest.importorskip("matplotlib", reason="render needs the viz extra (matplotlib)")
pytest.importorskip("mcap", reason="MCAP runs need the mcap extra")

from test_mcap_kitti import convert, write_tiny_sequence  # noqa: E402

from tisem.commands import main  # noqa: E402
from tisem.viz.compare import render_comparison  # noqa: E402


@pytest.mark.slow
def test_render_draws_an_mcap_run_like_its_kitti_twin(tmp_path):
    seq = write_tiny_sequence(tmp_path / "seq", n_scans=3, n_points=3000)
    convert(seq, tmp_path / "seq.mcap")
    common = ["--arch", "cpu", "--threads", "1", "--no-progress"]
    assert main(["map-kitti", "--data", str(seq), "--out", str(tmp_path / "kitti"), *common]) == 0
    assert (
        main(
            [
                "map-mcap",
                str(tmp_path / "seq.mcap"),
                "--gt-field",
                "gt_label",
                "--out",
                str(tmp_path / "mcap"),
                *common,
            ]
        )
        == 0
    )
    kitti = render_comparison(tmp_path / "kitti")
    mcap = render_comparison(tmp_path / "mcap")
    assert mcap["out"] == tmp_path / "mcap" / "compare.png" and mcap["out"].stat().st_size > 0
    assert mcap["scans"] == kitti["scans"] == [0, 1, 2]
    assert mcap["points"] == kitti["points"] > 0
    for panel in ("network", "map"):
        assert mcap["accuracy"][panel] == pytest.approx(kitti["accuracy"][panel], abs=2e-3)
    assert mcap["accuracy"]["map"] is not None


def test_render_refuses_a_run_json_without_input(tmp_path, capsys):
    (tmp_path / "run.json").write_text("{}")
    assert main(["render", str(tmp_path)]) == 2  # bad input, as every command says it
    assert "names no input ('data'" in capsys.readouterr().err
