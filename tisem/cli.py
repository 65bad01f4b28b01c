"""What the map apps share: their options, logging, the prologue of a run and its errors.

    args = cli.parse_run_args(parser, argv)          # the app's options + add_run_args
    return cli.run_app(body, args, log)              # errors -> one logged line, exit status

    def body(args):
        plan = cli.plan_run(args)                    # every option checked, the config (or the
                                                     # checkpoint's, --resume), the results folder
        ...open the input (inside `with cli.bad_input():`)...
        plan.start(args)                             # Taichi backend, then --overwrite clears
        result = plan.mapping_run(scans, args).run(show_progress=not args.no_progress)
        return plan.finish(result)                   # results/latest, exit status

Everything a user can get wrong is refused before anything is created: no results folder, no
change to results/latest. The folder itself appears with the run's first file and
results/latest points to it once the run has finished.

Exit status: 0 done; 1 the run could not finish (a full disk: `RunError`), what it wrote is
kept; 2 a bad command line, config or input (`AppError`, `ConfigError`, `DatasetError`); 130
interrupted (Ctrl-C, `RunInterrupted`).

The errors themselves are `tisem.app_errors` (here as `cli.AppError`, `cli.bad_input`), the
choice of the results folder `tisem.results_dir`.
"""

from __future__ import annotations

import argparse
import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from tisem.app_errors import AppError, BackendError, bad_input  # the apps use cli.AppError
from tisem.config import MODES, RunConfig, check_run_config, load_config
from tisem.errors import ConfigError, DatasetError, RunError, RunInterrupted
from tisem.outputs import clear_previous_run
from tisem.results_dir import choose_results_dir, point_latest

if TYPE_CHECKING:  # (the run imports the mapper, which starts Taichi)
    from tisem.checkpoint import Checkpoint
    from tisem.run import MappingRun, RunResult

EXIT_RUN_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for Ctrl-C
# options a resumed run takes from its checkpoint: dest -> flag
CONFIG_OPTIONS = {
    "config": "--config",
    "overrides": "--set",
    "mode": "--mode",
    "classes": "--classes",
}


# --------------------------------------------------------------------------- options


def add_run_args(parser: argparse.ArgumentParser) -> None:
    """The options every map app has: config, frame range, output, backend, checkpoints."""
    g = parser.add_argument_group("mapping")
    g.add_argument(
        "--mode", choices=MODES, help="method: st (default), adaptive, spatial, bki, csm"
    )
    g.add_argument(
        "--config", type=Path, help="YAML config (a RunConfig or just its mapper section)"
    )
    g.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set tau_s=1.5 (repeatable)",
    )
    g.add_argument(
        "--classes",
        type=Path,
        metavar="YAML",
        help="the label space, when not SemanticKITTI's 20 classes: a "
        "semantic-kitti.yaml-style file (labels, color_map, learning_map); "
        "num_classes follows from it",
    )
    g.add_argument("--first", type=int, help="first scan (inclusive)")
    g.add_argument("--last", type=int, help="last scan (inclusive)")
    g.add_argument(
        "--out",
        type=Path,
        help="output folder (default results/<timestamp>/); "
        "must be empty or new, unless --overwrite",
    )
    g.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the results of a previous run in --out (its config.yaml, "
        "run.json, metrics.json, map files, predictions, checkpoint and "
        "synthetic data; nothing else in the folder is touched)",
    )
    g.add_argument("--arch", choices=("cpu", "cuda"), default="cpu", help="Taichi backend")
    g.add_argument(
        "--threads",
        type=int,
        default=2,
        help="CPU threads for the kernels (>= 1; capped at the cores available)",
    )
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.add_argument(
        "--per-class",
        action="store_true",
        help="also print the IoU of every class after the results table",
    )
    g.add_argument("-v", "--verbose", action="store_true", help="also tisem's debug lines")
    g = parser.add_argument_group("checkpoints")
    g.add_argument(
        "--checkpoint-every",
        type=int,
        metavar="N",
        help="save the map and the metrics so far every N mapped scans, atomically, "
        "to <out>/checkpoint/ (default: never; a resumed run keeps its N)",
    )
    g.add_argument(
        "--resume",
        type=Path,
        metavar="DIR",
        help="continue the run of results folder DIR (or its checkpoint folder) with "
        "its stored config and input, in that folder unless --out is given; "
        "--last may extend it",
    )


def parse_run_args(
    parser: argparse.ArgumentParser,
    argv: list[str] | None = None,
    kept_on_resume: dict[str, str] | None = None,
) -> argparse.Namespace:
    """Parse a map app's command line (`add_run_args` options included). With --resume, the
    config options and the app's `kept_on_resume` ({dest: flag}: options stored in the
    checkpoint's run.json) must be left at their defaults: the run goes on as it started."""
    args = parser.parse_args(argv)
    if args.resume is not None:
        kept = {**CONFIG_OPTIONS, **(kept_on_resume or {})}
        given = [
            flag for dest, flag in kept.items() if getattr(args, dest) != parser.get_default(dest)
        ]
        if given:
            parser.error(
                f"--resume continues with the config and input stored in the "
                f"checkpoint: drop {' / '.join(given)}"
            )
    return args


def setup_logging(verbose: bool = False) -> None:
    """INFO lines of every logger; with `verbose` also tisem's own DEBUG lines (the libraries'
    debug chatter, matplotlib's font search and the like, stays out)."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("tisem").setLevel(logging.DEBUG if verbose else logging.NOTSET)


def finite_number(flag: str, value: float, low: float = 0.0) -> float:
    """A command-line number that must be finite and >= low; AppError otherwise."""
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= low):
        raise AppError(f"{flag} {value}: expected a finite number >= {low:g}")
    return float(value)


# --------------------------------------------------------------------------- errors


def run_app(
    body: Callable[[argparse.Namespace], int], args: argparse.Namespace, app_log: logging.Logger
) -> int:
    """Set up logging and run an app's `body(args)`; its errors are logged on `app_log` as
    one line each (no traceback), with the exit status of the module docstring."""
    setup_logging(args.verbose)
    try:
        return body(args)
    except (AppError, ConfigError, DatasetError) as exc:
        app_log.error("%s", exc)
        return EXIT_BAD_INPUT
    except RunError as exc:
        app_log.error("%s", exc)
        return EXIT_RUN_FAILED
    except RunInterrupted as exc:
        app_log.error("%s", exc)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        app_log.error("interrupted")
        return EXIT_INTERRUPTED
    finally:  # --classes set it for this run only
        from tisem.labels import use_label_space

        use_label_space(None)


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
    """--first / --last into `cfg`, checked with the rest of the config (ConfigError)."""
    if args.first is not None:
        cfg.first = args.first
    if args.last is not None:
        cfg.last = args.last
    check_run_config(cfg)


@dataclass
class RunPlan:
    """A map app's run before it starts: its config, with --resume the checkpoint it
    continues, and the results folder it will write (not made yet); `start` adds the
    backend."""

    cfg: RunConfig
    checkpoint: Checkpoint | None = None
    out_dir: Path | None = None
    device: str = ""
    threads: int = 2
    overwrite: bool = False
    classes: Path | None = None  # --classes: the label space's file
    link_latest: bool = False  # a results/<timestamp>/ folder: re-point results/latest

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
            raise AppError(
                f"resume: the checkpoint does not say where its input is; give {how_to_give}"
            )
        return Path(self.source[key])

    def start(self, args: argparse.Namespace) -> None:
        """Start the Taichi backend (first, so that one that cannot start costs nothing), then
        with --overwrite clear what a previous run left in the results folder."""
        try:
            self.device = init_backend(args.arch, self.threads)
        except BackendError as exc:
            raise AppError(str(exc)) from None
        if self.overwrite and self.out_dir.is_dir():
            removed = clear_previous_run(self.out_dir)
            if removed:
                logging.getLogger(__name__).info(
                    "--overwrite: removed %d files of a previous run from %s", removed, self.out_dir
                )

    def mapping_run(self, scans: Iterable, args: argparse.Namespace, **options) -> MappingRun:
        """The run over `scans` (new, or the checkpoint's continued), checkpointing every
        --checkpoint-every scans; `options`: `MappingRun`'s (sequence_name, total, ...)."""
        from tisem.run import MappingRun

        with bad_input("resume: " if self.checkpoint is not None else ""):
            if self.checkpoint is None:
                return MappingRun(
                    scans,
                    self.cfg,
                    self.out_dir,
                    checkpoint_every=args.checkpoint_every or 0,
                    **options,
                )
            return MappingRun.resume(
                scans,
                self.checkpoint,
                self.cfg,
                self.out_dir,
                checkpoint_every=args.checkpoint_every,
                **options,
            )

    def finish(self, result: RunResult) -> int:
        """After the run: results/latest points to it, unless mapping stopped early (then one
        line says so); the app's exit status."""
        if result.stopped:
            logging.getLogger(__name__).error(
                "mapping stopped %s; the %d scans mapped before it are scored and written in %s",
                result.stopped,
                result.metrics["scans"],
                self.out_dir,
            )
            return EXIT_RUN_FAILED
        if self.link_latest:
            point_latest(self.out_dir)
        return 0


def plan_run(args: argparse.Namespace) -> RunPlan:
    """Check every option, then the config from the options, or with --resume the
    checkpoint's (--first / --last may still change the frame range), and the results folder.
    Raises AppError / ConfigError; creates nothing."""
    with bad_input():
        from tisem.backend import usable_threads

        threads = usable_threads(args.threads)
    if args.checkpoint_every is not None and args.checkpoint_every < 1:
        raise AppError(
            f"--checkpoint-every {args.checkpoint_every}: expected a whole number "
            f">= 1 (mapped scans between checkpoints)"
        )
    if args.resume is None:
        with bad_input("config: "):
            plan = RunPlan(run_config_from_args(args))
    else:
        from tisem.checkpoint import load_checkpoint

        with bad_input("resume: "):
            ckpt = load_checkpoint(args.resume)
            cfg = ckpt.run_config()
            apply_frame_range(cfg, args)
        plan = RunPlan(cfg, ckpt)
    classes = args.classes if args.resume is None else plan.source.get("classes")
    if classes is not None:
        plan.classes = Path(classes).resolve()
        apply_label_space(plan.cfg, plan.classes, explicit=args.overrides)
    plan.threads = threads
    plan.overwrite = args.overwrite
    plan.out_dir, plan.link_latest = choose_results_dir(args.out, plan.checkpoint, args.overwrite)
    return plan


def apply_label_space(cfg: RunConfig, path: Path, explicit: Iterable[str] = ()) -> None:
    """Read the label space of `path`, make it the process's (tisem.labels) and give `cfg` its
    number of classes; AppError for a bad file or a --set num_classes that disagrees."""
    from tisem.label_space import load_label_space
    from tisem.labels import use_label_space

    with bad_input("--classes "):
        space = load_label_space(path)
    given = [
        a.split("=", 1)[1]
        for a in explicit
        if a.split("=", 1)[0].strip() in ("num_classes", "mapper.num_classes")
    ]
    if given and given[-1].strip() != str(space.num_classes):
        raise AppError(
            f"--set num_classes={given[-1]}: {path} defines {space.num_classes} "
            f"classes; leave num_classes out, it follows from --classes"
        )
    cfg.mapper.num_classes = space.num_classes
    with bad_input("config: "):
        check_run_config(cfg)
    use_label_space(space)


def init_backend(arch: str, threads: int) -> str:
    """Start Taichi as the options say; a backend that cannot start raises BackendError."""
    from tisem.backend import describe, init_taichi

    try:
        init_taichi(arch, threads=threads)
    except RuntimeError as exc:
        raise BackendError(str(exc)) from None
    return describe()
