"""`python apps/merge_maps.py ARGS` is `tisem merge-maps ARGS` (tisem/commands/merge_maps.py)."""

import sys

# the launcher's names are the command's: tests and scripts load it as a module
from tisem.commands.merge_maps import build_parser, main, parse_args  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
