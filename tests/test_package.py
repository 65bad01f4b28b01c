"""The package as a user installs it: the console script and its subcommands, `--version`,
the package list of pyproject.toml, help on every option, and the line a missing extra gives.
Nothing is built: the entry points are resolved from pyproject.toml and imported."""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

import tisem
from tisem.commands import COMMANDS, load, main

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
ISSUE_COMMANDS = {
    "map-kitti",
    "map-mcap",
    "kitti-to-mcap",
    "render",
    "make-synthetic",
    "dump-config",
    "merge-maps",
    "fleet",
    "batch",
}


def resolve(target: str):
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


def test_console_scripts_resolve_and_print_the_version(capsys):
    scripts = PYPROJECT["project"]["scripts"]
    assert set(scripts) == {"tisem"}
    console = resolve(scripts["tisem"])
    sys_argv = sys.argv
    sys.argv = ["tisem", "--version"]
    try:
        with pytest.raises(SystemExit) as stop:
            console()
    finally:
        sys.argv = sys_argv
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip() == f"tisem {tisem.__version__}"


def test_python_m_tisem_prints_the_version():
    done = subprocess.run(
        [sys.executable, "-m", "tisem", "--version"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"tisem {tisem.__version__}"


def test_every_subcommand_has_a_module_a_launcher_and_help_on_every_option(capsys):
    assert set(COMMANDS) == ISSUE_COMMANDS
    for command, (module_name, _) in COMMANDS.items():
        module = load(command)
        assert callable(module.main)
        assert (REPO / "apps" / f"{module_name}.py").is_file(), command
        parser = module.build_parser()
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            assert action.help, (
                f"tisem {command}: {action.option_strings or action.dest} has no help text"
            )
        with pytest.raises(SystemExit) as stop:
            main([command, "--help"])
        assert stop.value.code == 0
        assert capsys.readouterr().out.startswith(f"usage: tisem {command} "), command


def test_help_shows_defaults():
    text = load("map-kitti").build_parser().format_help()
    assert "(default: 2)" in text and "(default: cpu)" in text  # --threads, --arch


def test_pyproject_lists_every_package_and_maps_the_kernels():
    setuptools = PYPROJECT["tool"]["setuptools"]
    assert setuptools["package-dir"]["tisem.kernels"] == "kernels"
    folders = {
        ".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "tisem").rglob("__init__.py")
    }
    assert set(setuptools["packages"]) == folders | {"tisem.kernels"}
    assert not any(
        p.split(".")[0] in ("kernels", "benchmarks", "apps", "tests")
        for p in setuptools["packages"]
    )


def test_the_kernels_are_one_package_named_tisem_kernels():
    import tisem.kernels.layout as layout

    assert Path(layout.__file__).parent == REPO / "kernels"
    assert "kernels" not in sys.modules and "kernels.layout" not in sys.modules


def test_a_missing_extra_is_one_line_naming_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib fails
    monkeypatch.delitem(sys.modules, "tisem.viz.compare", raising=False)
    (tmp_path / "run.json").write_text("{}")
    assert main(["render", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "tisem: pictures (matplotlib) need the 'viz' extra (module 'matplotlib' is "
        'not installed): pip install "tisem[viz]"'
    ]


def test_extras_cover_the_optional_stacks():
    extras = PYPROJECT["project"]["optional-dependencies"]
    assert {"mcap", "viz", "ray", "test", "all"} <= set(extras)
    core = " ".join(PYPROJECT["project"]["dependencies"])
    assert "mcap" not in core and "matplotlib" not in core and "ray" not in core


def test_results_table_is_aligned_and_names_the_input():
    from tisem.report import results_table

    summary = {
        "miou": 0.41,
        "accuracy": 0.86,
        "wiou": 0.78,
        "oa_paper": 0.76,
        "points": 10,
        "per_class_iou": {"car": 0.8, "road": 0.9, "truck": 0.0, "person": None},
        "present_classes": ["car", "road"],
    }
    metrics = {
        "evaluated": True,
        "mode": "st",
        "input": summary,
        "final": summary,
        "online": summary,
        "scans": 5,
        "skipped": [],
        "seconds_per_scan": 0.07,
        "active_voxels": 1000,
    }
    text = results_table(metrics, per_class=True, input_name="labels (input)")
    tables = [
        [line for line in block.splitlines() if line.startswith("|")]
        for block in text.split("\n\n")
    ]
    main, per_class = tables[0], tables[1]
    assert len({len(line) for line in main}) == 1 and len({len(line) for line in per_class}) == 1
    assert main[2].startswith("| labels (input) ")
    names = [line.split("|")[1].strip() for line in per_class[2:]]
    assert names == ["car", "road", "truck *", "**mIoU (GT-present)**"]  # person: undefined


@pytest.mark.parametrize(
    "seconds, median_ms, said",
    [
        ([0.9, 0.05, 0.07, 0.06], 60.0, "(median after the first, which took 900 ms"),
        ([0.8, 0.05], 50.0, "(median after the first, which took 800 ms"),
        ([0.8], 800.0, "(its only scan, which loads the kernels)"),
    ],
)
def test_the_time_per_scan_gives_the_first_scan_apart(seconds, median_ms, said):
    """The first scan compiles or loads the kernels (a second or so): a run of two scans would
    otherwise say it maps at half that speed."""
    from types import SimpleNamespace

    from tisem.config import RunConfig
    from tisem.evaluate import Confusion
    from tisem.progress import RunProgress
    from tisem.report import results_table, run_metrics

    progress = RunProgress.start(20)
    progress.seconds = list(seconds)
    mapper = SimpleNamespace(live_voxels=10, stored_voxels=0)
    metrics = run_metrics(progress, Confusion(20), mapper, RunConfig())
    assert metrics["seconds_per_scan"] * 1000 == pytest.approx(median_ms)
    assert metrics["seconds_first_scan"] == seconds[0]
    assert f"; {median_ms:.1f} ms per scan {said}" in results_table(metrics)
    # metrics.json of older runs: the median of every scan, as they said
    older = {k: v for k, v in metrics.items() if k != "seconds_first_scan"}
    assert f"; {median_ms:.1f} ms per scan (median); " in results_table(older)


def test_verbose_shows_tisem_debug_lines_not_the_libraries():
    import logging

    from tisem.cli import setup_logging

    setup_logging(verbose=True)
    try:
        assert logging.getLogger("tisem.map_kitti").isEnabledFor(logging.DEBUG)
        assert not logging.getLogger("matplotlib.font_manager").isEnabledFor(logging.DEBUG)
    finally:
        setup_logging(verbose=False)
    assert not logging.getLogger("tisem.map_kitti").isEnabledFor(logging.DEBUG)


@pytest.mark.parametrize("command", [["-m", "tisem", "dump-config"], ["apps/dump_config.py"]])
def test_dump_config_writes_yaml_that_a_run_reads_back(tmp_path, command):
    """`tisem dump-config > my.yaml`, then `--config my.yaml`: stdout holds the YAML alone (in
    a fresh interpreter, where the config's checks import taichi for the first time)."""
    import yaml

    from tisem.config import load_config, to_dict

    def dump(*args: str) -> str:
        done = subprocess.run(
            [sys.executable, *command, *args],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=REPO,
        )
        assert done.returncode == 0, done.stderr
        return done.stdout

    out = dump()
    assert yaml.safe_load(out) == to_dict(load_config(None, []))
    mine = tmp_path / "my.yaml"
    mine.write_text(out)
    again = yaml.safe_load(dump("--config", str(mine), "--set", "tau_s=7.5"))
    assert again == to_dict(load_config(mine, ["tau_s=7.5"]))
    assert again != yaml.safe_load(out)
