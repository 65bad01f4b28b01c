"""Configuration and command-line mistakes: one line naming the key, the value and what is
allowed, exit status 2, and nothing created (no results folder, results/latest untouched).

Every mistake goes through `apps/map_kitti.py main(argv)` (or map_mcap's for its own options)
in a folder of its own, so that a default results/ folder would show; the rules themselves
are checked on `load_config` too.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os

import pytest
import taichi as ti
from test_pipeline import Records, load_app, run_app, tiny_sequence

from tisem.config import MAPPER_RULES, RUN_RULES, ConfigError, MapperConfig, RunConfig, load_config


@pytest.fixture(scope="module")
def one_scan(tmp_path_factory):
    return tiny_sequence(tmp_path_factory.mktemp("cfg") / "08", 1)


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """An empty working folder with an old results/latest link, as after an earlier run."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "results" / "old").mkdir(parents=True)
    os.symlink("old", tmp_path / "results" / "latest")
    return tmp_path


def assert_refused(rc, rec, workdir, *words):
    """Exit 2, one ERROR line (no traceback) holding `words`, nothing new on disk."""
    assert rc == 2, rec.text()
    errors = [r for r in rec.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1, [r.getMessage() for r in errors]
    message = errors[0].getMessage()
    assert errors[0].exc_info is None and "\n" not in message, message
    for word in words:
        assert word in message, f"{word!r} not in: {message}"
    assert sorted(p.name for p in workdir.iterdir()) == ["results"]
    assert sorted(p.name for p in (workdir / "results").iterdir()) == ["latest", "old"]
    assert os.readlink(workdir / "results" / "latest") == "old"
    return message


SET_MISTAKES = [
    # (the --set value, words of the one line)
    ("resolution_m=abc", ("resolution_m = 'abc'", "not a number", ">= 0.01")),
    ("first=abc", ("first = 'abc'", "not a number", "whole number")),
    ("resolution_m=0.05", ("ell_max_m = 1.2 at resolution_m = 0.05", "kernel reach")),
    ("resolution_m=100", ("resolution_m = 100", "out of range", "<= 10")),
    ("resolution_m=1e-4", ("resolution_m = 0.0001", "out of range")),
    ("tau_s=1e-300", ("tau_s = 1e-300", "out of range", ">= 1e-06")),
    ("num_classes=1000", ("num_classes = 1000", "<= 31")),
    ("num_classes=2.5", ("num_classes = 2.5", "not a whole number")),
    ("num_classes=5", ("num_classes = 5", "train ids 0..19", ">= 20")),
    ("max_live_blocks=-5", ("max_live_blocks = -5", "out of range", ">= 1")),
    ("window_xy_m=.inf", ("window_xy_m = inf", "not a finite number")),
    ("prior=.nan", ("prior = nan", "not a finite number")),
    ("sigma0=-1", ("sigma0 = -1", "> 0")),
    ("input=foo", ("input = 'foo'", "one of predictions, labels")),
    ("mode=fast", ("mode = 'fast'", "one of st, adaptive")),
    ("store_dir=/nonexistent/spill", ("store_dir = '/nonexistent/spill'", "does not exist")),
    ("window_xy_m=50", ("window_xy_m=50.0", "must hold the scan")),
    ("window_xy_m=20000", ("window_xy_m = 20000", "top cells")),
    ("min_range_m=90", ("min_range_m = 90", "below max_range_m = 80")),
    ("ell_min_m=2", ("ell_min_m = 2", "must not exceed ell_max_m")),
    ("online_eval=maybe", ("online_eval = 'maybe'", "true or false")),
    ("last=-1", ("last = -1", "out of range")),
    ("no_such_key=1", ("unknown key 'no_such_key'; known: ",)),
    ("tau_ss=3", ("unknown key 'tau_ss' (did you mean tau_s?); known: ",)),
    ("mapper.firts=3", ("unknown key 'firts'; known: ",)),
    ("mapper.first=3", ("first is a key of the run, not of its mapper section: --set first=3",)),
    ("firts=3", ("unknown key 'firts' (did you mean first?); known: ",)),
    ("resolution_m", ("expected key=value",)),
    ("resolution_m=[0.2", ("not a YAML value",)),
]


@pytest.mark.parametrize("assignment,words", SET_MISTAKES, ids=[m[0] for m in SET_MISTAKES])
def test_a_set_mistake_is_one_line_and_creates_nothing(one_scan, workdir, assignment, words):
    rc, rec = run_app(["--data", one_scan, "--no-progress", "--set", assignment])
    assert_refused(rc, rec, workdir, *words)


CONFIG_FILES = [
    ("quoted", 'resolution_m: "0.2"\n', ("resolution_m = '0.2'", "quoted string")),
    ("syntax", "resolution_m: [0.2\n", ("not valid YAML", "line 2")),
    (
        "python tag",
        "mapper: !!python/object/apply:os.system ['true']\n",
        ("not valid YAML", "python/object/apply"),
    ),
    ("not a mapping", "- 1\n- 2\n", ("expected a mapping", "list")),
    ("section", "mapper: 3\n", ("mapper must be a mapping",)),
    ("typo", "mapper:\n  tau_ss: 3\n", ("mapper: unknown key 'tau_ss' (did you mean tau_s?)",)),
    ("nan", "prior: .nan\n", ("prior = nan", "not a finite number")),
    ("missing store_dir", "store_dir: /nonexistent/spill\n", ("does not exist",)),
]


@pytest.mark.parametrize(
    "text,words", [c[1:] for c in CONFIG_FILES], ids=[c[0] for c in CONFIG_FILES]
)
def test_a_config_file_mistake_is_one_line_and_creates_nothing(
    one_scan, workdir, tmp_path_factory, text, words
):
    config = tmp_path_factory.mktemp("config") / "bad.yaml"
    config.write_text(text)
    rc, rec = run_app(["--data", one_scan, "--no-progress", "--config", config])
    message = assert_refused(rc, rec, workdir, *words)
    assert "bad.yaml" in message


@pytest.mark.parametrize(
    "argv,words",
    [
        (["--threads", "0"], ("--threads 0", ">= 1")),
        (["--threads", "-1"], ("--threads -1", ">= 1")),
        (["--checkpoint-every", "0"], ("--checkpoint-every 0", ">= 1")),
        (["--first", "3", "--last", "1"], ("last = 1", "before first = 3")),
        (["--config", "missing.yaml"], ("missing.yaml", "cannot read the config file")),
    ],
    ids=["threads 0", "threads -1", "checkpoint-every 0", "last before first", "no config"],
)
def test_a_command_line_mistake_is_one_line_and_creates_nothing(one_scan, workdir, argv, words):
    rc, rec = run_app(["--data", one_scan, "--no-progress", *argv])
    assert_refused(rc, rec, workdir, *words)


def test_out_naming_a_file_is_refused(one_scan, workdir):
    (workdir / "results" / "old" / "notes.txt").write_text("mine")
    rc, rec = run_app(
        ["--data", one_scan, "--no-progress", "--out", workdir / "results" / "old" / "notes.txt"]
    )
    assert_refused(rc, rec, workdir, "notes.txt: is a file, not a folder")
    assert (workdir / "results" / "old" / "notes.txt").read_text() == "mine"


def test_tf_tolerance_nan_is_refused_before_the_recording_is_read(workdir):
    rec_path = workdir / "results" / "old" / "drive.mcap"
    rc, rec = run_app_named("map_mcap", [rec_path, "--no-progress", "--tf-tolerance-ms", "nan"])
    assert_refused(rc, rec, workdir, "--tf-tolerance-ms nan", "finite number >= 0")


def run_app_named(name, argv):
    """`apps/<name>.py main(argv)` with every log record kept (test_pipeline.run_app's, for
    any app)."""
    rec = Records()
    root = logging.getLogger()
    old = root.level
    root.addHandler(rec)
    root.setLevel(logging.INFO)
    try:
        rc = load_app(name).main([str(a) for a in argv])
    finally:
        root.removeHandler(rec)
        root.setLevel(old)
        ti.reset()
    return rc, rec


@pytest.mark.slow
def test_threads_above_the_cores_are_capped_with_one_line(tmp_path):
    """--threads 100000 starts as many threads as there are cores, and says so once."""
    from tisem.backend import available_cores

    seq = tiny_sequence(tmp_path / "08", 2)
    out = tmp_path / "out"
    rc, rec = run_app(["--data", seq, "--out", out, "--no-progress", "--threads", "100000"])
    assert rc == 0, rec.text()
    cores = available_cores()
    said = [t for t in rec.text(logging.WARNING) if "--threads 100000" in t]
    assert said == [
        f"--threads 100000: this machine has {cores} cores available; using {cores} threads"
    ]
    assert json.loads((out / "run.json").read_text())["threads"] == cores


# --------------------------------------------------------------------------- the rules


def test_every_config_field_has_one_rule():
    assert set(MAPPER_RULES) == {f.name for f in dataclasses.fields(MapperConfig)}
    assert set(RUN_RULES) == {f.name for f in dataclasses.fields(RunConfig)}


def test_yaml_numbers_are_what_a_user_means(tmp_path):
    """1e-1 is a number (YAML 1.1 reads it as a string), as are 5e0 and 1.5E+1; ints become
    floats where floats belong, whole floats ints where ints do."""
    config = tmp_path / "c.yaml"
    config.write_text("tau_s: 5e-1\nsigma0: 2\nmax_live_blocks: 1.0e4\nprior: 1.5E+1\n")
    cfg = load_config(config, ["ell_min_m=3e-1", "first=2e0"])
    assert cfg.mapper.tau_s == 0.5 and cfg.mapper.sigma0 == 2.0
    assert isinstance(cfg.mapper.sigma0, float)
    assert cfg.mapper.max_live_blocks == 10_000 and isinstance(cfg.mapper.max_live_blocks, int)
    assert cfg.mapper.prior == 15.0 and cfg.mapper.ell_min_m == 0.3 and cfg.first == 2


def test_validate_refuses_what_a_program_sets_directly():
    cfg = MapperConfig(tau_s=float("nan"))
    with pytest.raises(ConfigError, match=r"^tau_s = nan: not a finite number"):
        cfg.validate()
    with pytest.raises(ConfigError, match=r"^num_classes = True: not a number"):
        MapperConfig(num_classes=True).validate()


def test_a_sweep_mistake_is_named_as_the_sweeps_and_a_set_mistake_as_the_sets():
    """`tisem batch --sweep tau=1,5` is not a --set: the line names the option it came from."""
    from tisem.batch import plan_cells
    from tisem.errors import ConfigError

    with pytest.raises(ConfigError, match=r"^--sweep tau=1: unknown key 'tau' \(did you mean"):
        plan_cells([], [], ["tau=1,5"])
    with pytest.raises(ConfigError, match=r"^--sweep: tau_s = -1: "):
        plan_cells([], [], ["tau_s=-1,5"])
    with pytest.raises(ConfigError, match=r"^--set tau=1: unknown key"):
        plan_cells([], ["tau=1"], ["tau_s=1,5"])
    assert len(plan_cells([], ["mode=bki"], ["tau_s=1,5"])) == 0  # (no logs: no cells)
