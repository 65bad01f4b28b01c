"""Errors and skip records shared by readers and the mapping run.

A reader raises `DatasetError` when nothing can be mapped (no poses at all, no `Tr`),
and `ScanError` for one bad scan; iterating a reader turns a `ScanError` into a `SkippedScan`,
which the run (`tisem.run.MappingRun`) reports and passes over, mapping the rest.
"""
from __future__ import annotations

from dataclasses import dataclass


class DatasetError(ValueError):
    """The input as a whole cannot be read (names the file and the problem)."""


class ScanError(ValueError):
    """One scan cannot be used (names the file and the problem); the rest still can."""

    def __init__(self, message: str, index: int | None = None, name: str = ""):
        super().__init__(message)
        self.index = index
        self.name = name


@dataclass
class SkippedScan:
    """A scan that was not mapped (its reader or the mapper refused it), and why."""

    index: int
    name: str
    reason: str
