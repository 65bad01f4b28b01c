"""Print the config a run would use, as YAML: the defaults, a --config file, --set overrides.

    tisem dump-config > my.yaml                    # every key with its default, to edit
    tisem dump-config --config my.yaml --set tau_s=2.5 --mode bki
    tisem map-kitti --config my.yaml ...           # the run uses exactly this

Every value is checked as a run would check it: a bad key or value is one line and exit 2.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

import yaml

from tisem import cli
from tisem.commands import entry, new_parser
from tisem.config import MODES, load_config, to_dict

log = logging.getLogger("tisem.dump_config")


def build_parser() -> argparse.ArgumentParser:
    p = new_parser("dump_config", __doc__)
    p.add_argument("--config", type=Path, help="YAML config (a RunConfig or its mapper section)")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set tau_s=1.5 (repeatable)",
    )
    p.add_argument("--mode", choices=MODES, help="method (default st)")
    p.add_argument("-v", "--verbose", action="store_true", help="also tisem's debug lines")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def dump(args: argparse.Namespace) -> int:
    # the config's checks import taichi, whose first import prints a banner on stdout: here
    # stdout is the YAML a user redirects to a file
    os.environ["ENABLE_TAICHI_HEADER_PRINT"] = "0"
    overrides = [*args.overrides, *([f"mode={args.mode}"] if args.mode else [])]
    with cli.bad_input("config: "):
        cfg = load_config(args.config, overrides)
    sys.stdout.write(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    return 0


@entry
def main(argv: list[str] | None = None) -> int:
    return cli.run_app(dump, parse_args(argv), log)


if __name__ == "__main__":
    sys.exit(main())
