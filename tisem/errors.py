"""Errors and skip records shared by readers and the pipeline.

A reader raises `DatasetError` when nothing can be mapped (no poses at all, no `Tr`),
and `ScanError` for one bad scan; the pipeline turns a `ScanError` into a `SkippedScan`,
reports it and goes on with the rest of the sequence.
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
    """A scan the pipeline did not map, and why."""

    index: int
    name: str
    reason: str
