"""The `tisem` command: one subcommand per app (`tisem map-kitti ...`, `tisem --version`).

Each subcommand is a module here with `build_parser()` and `main(argv) -> exit status` (wrapped
in `entry`); `python apps/<name>.py` launches the same module. Modules are imported only when
their subcommand runs, so `tisem --help` starts no Taichi and needs no extra.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable

from tisem.extras import missing_extra

# subcommand -> (module under tisem.commands, one line for `tisem --help`)
COMMANDS = {
    "map-kitti": ("map_kitti", "map a SemanticKITTI sequence (or the synthetic demo) and score it"),
    "map-mcap": ("map_mcap", "map a ROS 2 recording of labelled point clouds"),
    "kitti-to-mcap": ("kitti_to_mcap", "write a SemanticKITTI sequence as a ROS 2 recording"),
    "render": ("render", "draw pictures of a results folder"),
    "make-synthetic": (
        "make_synthetic",
        "write a synthetic labelled street (SemanticKITTI layout)",
    ),
    "dump-config": ("dump_config", "print the resolved config as YAML"),
    "merge-maps": ("merge_maps", "merge maps of one world into one tiled map"),
    "fleet": ("fleet", "map several logs on Ray and merge their maps"),
    "batch": ("batch", "run sequences x configs on Ray; one table of metrics"),
}
EXIT_BAD_INPUT = 2
_prog_prefix = ""  # "tisem " while a subcommand runs under the `tisem` command


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """The module docstring as written, and every option's default after its help (unless the
    help already says it, or there is none to say)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            "default" in text
            or default in (None, False, [], argparse.SUPPRESS)
            or action.nargs == 0
        ):
            return text
        return f"{text} (default: %(default)s)"


def new_parser(name: str, doc: str) -> argparse.ArgumentParser:
    """The argument parser of subcommand `name` (a module name, e.g. map_kitti), described by
    its module docstring `doc`."""
    prog = f"{_prog_prefix}{name.replace('_', '-')}" if _prog_prefix else None
    return argparse.ArgumentParser(prog=prog, description=doc, formatter_class=HelpFormatter)


def entry(main: Callable[[list[str] | None], int]) -> Callable[[list[str] | None], int]:
    """Wrap a subcommand's `main`: a missing optional dependency ends it with one line naming
    the extra to install (exit status 2), not an import traceback."""

    def wrapped(argv: list[str] | None = None) -> int:
        try:
            return main(argv)
        except ImportError as exc:
            missing = missing_extra(exc)
            if missing is None:
                raise
            print(f"tisem: {missing}", file=sys.stderr)
            return EXIT_BAD_INPUT

    wrapped.__doc__, wrapped.__name__ = main.__doc__, main.__name__
    return wrapped


def load(command: str):
    """The module of a subcommand (`map-kitti` -> tisem.commands.map_kitti)."""
    return importlib.import_module(f"tisem.commands.{COMMANDS[command][0]}")


def top_parser() -> argparse.ArgumentParser:
    from tisem import __version__

    lines = "\n".join(f"  {name:15s} {text}" for name, (_, text) in COMMANDS.items())
    p = argparse.ArgumentParser(
        prog="tisem",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="3D semantic maps from labelled LiDAR scans (Bayesian kernel inference "
        "with temporal decay, on Taichi sparse fields).",
        epilog=f"commands:\n{lines}\n\n`tisem COMMAND --help` shows a command's options.",
    )
    p.add_argument("--version", action="version", version=f"tisem {__version__}")
    p.add_argument("command", choices=COMMANDS, metavar="COMMAND", help="one of the commands below")
    return p


def main(argv: list[str] | None = None) -> int:
    """`tisem COMMAND [OPTIONS]`: run one subcommand; its exit status."""
    global _prog_prefix
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    if not argv or argv[0] not in COMMANDS:
        parser = top_parser()
        parser.parse_args(argv[:1])  # --help, --version, or an unknown command
        parser.print_help()
        return EXIT_BAD_INPUT
    _prog_prefix = "tisem "
    try:
        return load(argv[0]).main(argv[1:])
    finally:
        _prog_prefix = ""


def console() -> None:
    """The `tisem` console script."""
    sys.exit(main())
