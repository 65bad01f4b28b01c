"""Errors and skip records shared by readers, the config and the mapping run.

A reader raises `DatasetError` when nothing can be mapped (no poses at all, no `Tr`),
and `ScanError` for one bad scan; iterating a reader turns a `ScanError` into a `SkippedScan`,
which the run (`tisem.run.MappingRun`) reports and passes over, mapping the rest.
`ConfigError` names a config key, its value and what is allowed. The run ends early with
`RunInterrupted` (Ctrl-C, acted on between scans) or `RunError` (a disk that cannot take the
outputs or a checkpoint); every message is one line.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


class DatasetError(ValueError):
    """The input as a whole cannot be read (names the file and the problem)."""


class ScanError(ValueError):
    """One scan cannot be used (names the file and the problem); the rest still can."""

    def __init__(self, message: str, index: int | None = None, name: str = ""):
        super().__init__(message)
        self.index = index
        self.name = name


class ConfigError(ValueError):
    """A configuration value that cannot work: the message names the key, the value and what
    is allowed."""


class NothingMapped(DatasetError):
    """Every scan of the input was skipped: there is no map to score or write."""


class RunError(RuntimeError):
    """The run cannot go on (a full disk while writing outputs or a checkpoint, a spill folder
    that cannot take the store): one line saying what failed and what was kept."""


class RunInterrupted(Exception):
    """The run was asked to stop (Ctrl-C) and stopped at a scan boundary.

    last_index: `Scan.index` of the last integrated scan (None: none yet); checkpoint: the
    checkpoint written on the way out (None when checkpoints are off); out_dir: the results
    folder.
    """

    def __init__(self, last_index: int | None, checkpoint: Path | None, out_dir: Path):
        self.last_index = last_index
        self.checkpoint = checkpoint
        self.out_dir = out_dir
        where = "before the first scan" if last_index is None else f"after scan {last_index}"
        if checkpoint is not None:
            message = f"interrupted {where}; continue with --resume {out_dir}"
        else:
            message = (
                f"interrupted {where}; nothing to resume from (checkpoints are off: "
                f"--checkpoint-every N saves them)"
            )
        super().__init__(message)


def os_error_text(exc: OSError) -> str:
    """An OSError as a short phrase: its reason and the file, without the errno brackets."""
    reason = exc.strerror or str(exc)
    return f"{reason} ({exc.filename})" if exc.filename else reason


@dataclass
class SkippedScan:
    """A scan that was not mapped (its reader or the mapper refused it), and why."""

    index: int
    name: str
    reason: str

    def line(self) -> str:
        """'skipped scan N (name): reason', the name left out where the reason starts with it
        (a reader's reason names its file already)."""
        named = self.name and not self.reason.startswith(self.name)
        return f"skipped scan {self.index}{f' ({self.name})' if named else ''}: {self.reason}"
