"""`python apps/dump_config.py ARGS` is `tisem dump-config ARGS` (tisem/commands/dump_config.py)."""

import sys

# the launcher's names are the command's: tests and scripts load it as a module
from tisem.commands.dump_config import build_parser, main, parse_args  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
