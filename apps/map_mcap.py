"""`python apps/map_mcap.py ARGS` is `tisem map-mcap ARGS` (tisem/commands/map_mcap.py)."""

import sys

# the launcher's names are the command's: tests and scripts load it as a module
from tisem.commands.map_mcap import build_parser, main, parse_args  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
