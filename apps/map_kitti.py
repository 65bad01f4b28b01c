"""`python apps/map_kitti.py ARGS` is `tisem map-kitti ARGS` (tisem/commands/map_kitti.py)."""

import sys

# the launcher's names are the command's: tests and scripts load it as a module
from tisem.commands.map_kitti import build_parser, main, parse_args  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
