"""Command-line plumbing shared by the apps: options, logging, backend, results folder."""
from __future__ import annotations

import argparse
import datetime as _dt
import logging
import os
from pathlib import Path

from tisem.config import MODES, RunConfig, load_config


def add_common_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("mapping")
    g.add_argument("--mode", choices=MODES, help="method: st (default), adaptive, spatial, bki, csm")
    g.add_argument("--config", type=Path, help="YAML config (a RunConfig or just its mapper section)")
    g.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set tau_s=1.5 (repeatable)")
    g.add_argument("--first", type=int, help="first scan (inclusive)")
    g.add_argument("--last", type=int, help="last scan (inclusive)")
    g.add_argument("--out", type=Path, help="output folder (default results/<timestamp>/)")
    g.add_argument("--arch", choices=("cpu", "cuda"), default="cpu", help="Taichi backend")
    g.add_argument("--threads", type=int, default=2, help="CPU threads for the kernels")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.add_argument("-v", "--verbose", action="store_true")


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")


def run_config_from_args(args) -> RunConfig:
    overrides = list(args.overrides)
    if args.mode:
        overrides.append(f"mode={args.mode}")
    cfg = load_config(args.config, overrides)
    if args.first is not None:
        cfg.first = args.first
    if args.last is not None:
        cfg.last = args.last
    return cfg


class BackendError(RuntimeError):
    """The requested Taichi backend cannot start (e.g. --arch cuda without a GPU)."""


def init_backend(args) -> str:
    """Start Taichi as the options say; a backend that cannot start raises BackendError."""
    from tisem.backend import describe, init_taichi
    try:
        init_taichi(args.arch, threads=args.threads)
    except RuntimeError as exc:
        raise BackendError(str(exc)) from None
    return describe()


def results_dir(args, root: str | Path = "results") -> Path:
    """`--out`, or results/<timestamp>/ with a `latest` link next to it."""
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        return args.out
    root = Path(root)
    stamp = _dt.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    out = root / stamp
    k = 1
    while out.exists():
        out = root / f"{stamp}_{k}"
        k += 1
    out.mkdir(parents=True)
    latest = root / "latest"
    try:
        if latest.is_symlink() or latest.exists():
            latest.unlink()
        os.symlink(out.name, latest)
    except OSError:
        pass   # a filesystem without links: the timestamped folder is what counts
    return out
