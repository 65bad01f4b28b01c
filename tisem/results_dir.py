"""Where a map app writes: the results folder it chooses, and results/latest.

A run writes into --out, the folder of the run it resumes, or a new results/<timestamp>/;
results/latest points to the newest finished timestamped run. Apart from `tisem.cli` because
the Ray apps (`tisem.ray_cli`: fleet, batch) name their new folders the same way without the
map apps' prologue.
"""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path
from typing import TYPE_CHECKING

from tisem.app_errors import AppError
from tisem.outputs import is_results_folder

if TYPE_CHECKING:
    from tisem.checkpoint import Checkpoint

RESULTS_ROOT = "results"


def choose_results_dir(
    out: Path | None,
    checkpoint: Checkpoint | None,
    overwrite: bool,
    root: str | Path = RESULTS_ROOT,
) -> tuple[Path, bool]:
    """The folder the run will write (not made here) and whether results/latest is to point
    to it: --out; else the resumed run's folder; else a new results/<timestamp>/.

    --out must be a folder that is new or empty, or the folder of the run being resumed, or,
    with --overwrite, a previous run's results folder; AppError otherwise."""
    resumed = checkpoint.results_dir.resolve() if checkpoint is not None else None
    if out is None:
        if resumed is not None:
            return checkpoint.results_dir, False
        return new_timestamped_dir(Path(root)), True
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise AppError(f"--out {out}: is a file, not a folder")
    if not out.is_dir() or out.resolve() == resumed:
        return out, False
    contents = sorted(p.name for p in out.iterdir())
    if not contents:
        return out, False
    shown = ", ".join(contents[:5]) + (", ..." if len(contents) > 5 else "")
    if not overwrite:
        raise AppError(
            f"--out {out}: the folder is not empty ({shown}); give --overwrite to "
            f"replace a previous run's results there, or another --out"
        )
    if not is_results_folder(out):
        raise AppError(
            f"--out {out}: the folder is not empty ({shown}) and holds no tisem "
            f"results (no run.json) for --overwrite to replace; choose another --out"
        )
    return out, False


def new_timestamped_dir(root: Path) -> Path:
    """results/<timestamp>/ (with a suffix when taken); not made here."""
    stamp = _dt.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    out = root / stamp
    k = 1
    while out.exists():
        out = root / f"{stamp}_{k}"
        k += 1
    return out


def point_latest(out: Path) -> None:
    """results/latest -> `out` (a sibling), replacing the old link."""
    latest = out.parent / "latest"
    try:
        if latest.is_symlink() or latest.exists():
            latest.unlink()
        os.symlink(out.name, latest)
    except OSError:
        pass  # a filesystem without links: the timestamped folder is what counts
