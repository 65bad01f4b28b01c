"""`python apps/kitti_to_mcap.py ARGS` is `tisem kitti-to-mcap ARGS`
(tisem/commands/kitti_to_mcap.py)."""

import sys

# the launcher's names are the command's: tests and scripts load it as a module
from tisem.commands.kitti_to_mcap import build_parser, main, parse_args  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
