"""What the map apps share: their options, logging, the prologue of a run and its errors.

    args = cli.parse_run_args(parser, argv)          # the app's options + add_run_args
    return cli.run_app(body, args, log)              # AppError -> one logged line, exit 2

    def body(args):
        plan = cli.plan_run(args)                    # the config, or the checkpoint's (--resume)
        ...open the input (inside `with cli.bad_input():`)...
        plan.start(args)                             # Taichi backend, then the results folder
        result = plan.mapping_run(scans, args).run(show_progress=not args.no_progress)
"""
from __future__ import annotations

import argparse
import datetime as _dt
import logging
import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable, Iterator

from tisem.config import MODES, RunConfig, load_config

if TYPE_CHECKING:                      # (the run imports the mapper, which starts Taichi)
    from tisem.checkpoint import Checkpoint
    from tisem.run import MappingRun

EXIT_BAD_INPUT = 2
# options a resumed run takes from its checkpoint: dest -> flag
CONFIG_OPTIONS = {"config": "--config", "overrides": "--set", "mode": "--mode"}


# --------------------------------------------------------------------------- options

def add_run_args(parser: argparse.ArgumentParser) -> None:
    """The options every map app has: config, frame range, output, backend, checkpoints."""
    g = parser.add_argument_group("mapping")
    g.add_argument("--mode", choices=MODES,
                   help="method: st (default), adaptive, spatial, bki, csm")
    g.add_argument("--config", type=Path,
                   help="YAML config (a RunConfig or just its mapper section)")
    g.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set tau_s=1.5 (repeatable)")
    g.add_argument("--first", type=int, help="first scan (inclusive)")
    g.add_argument("--last", type=int, help="last scan (inclusive)")
    g.add_argument("--out", type=Path, help="output folder (default results/<timestamp>/)")
    g.add_argument("--arch", choices=("cpu", "cuda"), default="cpu", help="Taichi backend")
    g.add_argument("--threads", type=int, default=2, help="CPU threads for the kernels")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.add_argument("-v", "--verbose", action="store_true")
    g = parser.add_argument_group("checkpoints")
    g.add_argument("--checkpoint-every", type=int, metavar="N",
                   help="save the map and the metrics so far every N mapped scans, atomically, "
                        "to <out>/checkpoint/ (default: never; a resumed run keeps its N)")
    g.add_argument("--resume", type=Path, metavar="DIR",
                   help="continue the run of results folder DIR (or its checkpoint folder) with "
                        "its stored config and input, in that folder unless --out is given; "
                        "--last may extend it")


def parse_run_args(parser: argparse.ArgumentParser, argv: list[str] | None = None,
                   kept_on_resume: dict[str, str] | None = None) -> argparse.Namespace:
    """Parse a map app's command line (`add_run_args` options included). With --resume, the
    config options and the app's `kept_on_resume` ({dest: flag}: options stored in the
    checkpoint's run.json) must be left at their defaults: the run goes on as it started."""
    args = parser.parse_args(argv)
    if args.resume is not None:
        kept = {**CONFIG_OPTIONS, **(kept_on_resume or {})}
        given = [flag for dest, flag in kept.items()
                 if getattr(args, dest) != parser.get_default(dest)]
        if given:
            parser.error(f"--resume continues with the config and input stored in the "
                         f"checkpoint: drop {' / '.join(given)}")
    return args


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")


# --------------------------------------------------------------------------- errors

class AppError(Exception):
    """A bad command line or input: the app logs this one line and exits with status 2."""


class BackendError(RuntimeError):
    """The requested Taichi backend cannot start (e.g. --arch cuda without a GPU)."""


@contextmanager
def bad_input(prefix: str = "") -> Iterator[None]:
    """Inside: the errors that mean 'this input cannot be used' (a config key, a value, a
    file, a `DatasetError`) become an `AppError` with their message (after `prefix`)."""
    try:
        yield
    except (KeyError, ValueError, OSError) as exc:
        raise AppError(f"{prefix}{exc}") from None


def run_app(body: Callable[[argparse.Namespace], int], args: argparse.Namespace,
            app_log: logging.Logger) -> int:
    """Set up logging and run an app's `body(args)`; an `AppError` is logged on `app_log` as
    one line (no traceback) and gives exit status 2."""
    setup_logging(args.verbose)
    try:
        return body(args)
    except AppError as exc:
        app_log.error("%s", exc)
        return EXIT_BAD_INPUT


# --------------------------------------------------------------------------- the prologue

def run_config_from_args(args: argparse.Namespace) -> RunConfig:
    """--config, --set, --mode, --first, --last as a validated `RunConfig`."""
    overrides = list(args.overrides)
    if args.mode:
        overrides.append(f"mode={args.mode}")
    cfg = load_config(args.config, overrides)
    apply_frame_range(cfg, args)
    return cfg


def apply_frame_range(cfg: RunConfig, args: argparse.Namespace) -> None:
    if args.first is not None:
        cfg.first = args.first
    if args.last is not None:
        cfg.last = args.last


@dataclass
class RunPlan:
    """A map app's run before it starts: its config and, with --resume, the checkpoint it
    continues; `start` adds the backend and the results folder."""

    cfg: RunConfig
    checkpoint: Checkpoint | None = None
    out_dir: Path | None = None
    device: str = ""

    @property
    def source(self) -> dict:
        """What the resumed run's run.json says (data, options, sequence); {} for a new run."""
        return self.checkpoint.source if self.checkpoint is not None else {}

    def input_path(self, given: Path | None, key: str, how_to_give: str) -> Path | None:
        """The input to read: `given` on the command line, else for a resumed run the one its
        run.json names under `key` (AppError when it names none), else None."""
        if given is not None or self.checkpoint is None:
            return given
        if self.source.get(key) is None:
            raise AppError(f"resume: the checkpoint does not say where its input is; give "
                           f"{how_to_give}")
        return Path(self.source[key])

    def start(self, args: argparse.Namespace) -> None:
        """Start the Taichi backend (first, so that one that cannot start costs nothing), then
        make the results folder: --out, the resumed run's folder, or results/<timestamp>/."""
        try:
            self.device = init_backend(args)
        except BackendError as exc:
            raise AppError(str(exc)) from None
        out = args.out
        if out is None and self.checkpoint is not None:
            out = self.checkpoint.results_dir
        self.out_dir = results_dir(out)

    def mapping_run(self, scans: Iterable, args: argparse.Namespace, **options) -> MappingRun:
        """The run over `scans` (new, or the checkpoint's continued), checkpointing every
        --checkpoint-every scans; `options`: `MappingRun`'s (sequence_name, total, ...)."""
        from tisem.run import MappingRun
        if self.checkpoint is None:
            return MappingRun(scans, self.cfg, self.out_dir,
                              checkpoint_every=args.checkpoint_every or 0, **options)
        return MappingRun.resume(scans, self.checkpoint, self.cfg, self.out_dir,
                                 checkpoint_every=args.checkpoint_every, **options)


def plan_run(args: argparse.Namespace) -> RunPlan:
    """The config from the options, or with --resume the checkpoint's (--first / --last may
    still change the frame range). Raises AppError."""
    if args.resume is None:
        with bad_input("config: "):
            return RunPlan(run_config_from_args(args))
    from tisem.checkpoint import load_checkpoint
    with bad_input("resume: "):
        ckpt = load_checkpoint(args.resume)
        cfg = ckpt.run_config()
    apply_frame_range(cfg, args)
    return RunPlan(cfg, ckpt)


def init_backend(args: argparse.Namespace) -> str:
    """Start Taichi as the options say; a backend that cannot start raises BackendError."""
    from tisem.backend import describe, init_taichi
    try:
        init_taichi(args.arch, threads=args.threads)
    except RuntimeError as exc:
        raise BackendError(str(exc)) from None
    return describe()


def results_dir(out: Path | None, root: str | Path = "results") -> Path:
    """`out` (made if missing), or results/<timestamp>/ with a `latest` link next to it."""
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        return out
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
