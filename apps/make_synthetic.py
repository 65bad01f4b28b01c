"""`python apps/make_synthetic.py ARGS` is `tisem make-synthetic ARGS`
(tisem/commands/make_synthetic.py)."""

import sys

# the launcher's names are the command's: tests and scripts load it as a module
from tisem.commands.make_synthetic import build_parser, main, parse_args  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
