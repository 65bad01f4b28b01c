"""`python apps/fleet.py ARGS` is `tisem fleet ARGS` (tisem/commands/fleet.py)."""

import sys

# the launcher's names are the command's: tests and scripts load it as a module
from tisem.commands.fleet import build_parser, main, parse_args  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
