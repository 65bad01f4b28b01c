"""What reading an MCAP file could not use, and why: `Loss` records and the `ReadReport`."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from mcap.records import Channel

from tisem.errors import SkippedScan


def lost_on(channel: Channel | None, channel_id: int) -> str:
    """The name a loss counts a channel's messages under: its topic, or "channel N" when its
    Channel record has not been read (yet)."""
    return channel.topic if channel is not None else f"channel {channel_id}"


def unnamed_channel_id(name: str) -> int | None:
    """N of a loss's "channel N" (`lost_on`), None for a topic's name."""
    word, _, number = name.partition(" ")
    return int(number) if word == "channel" and number.isdigit() else None


@dataclass
class Loss:
    """One piece of the file that could not be used (or could not be trusted)."""

    where: str  # e.g. "chunk at byte 1234 (log time 1.0-1.2 s)"
    what: str  # why it was lost
    messages: int | None = None  # how many messages it held; None when it held none or
    uncounted: bool = False  # ... when how many is unknown (then `uncounted`)
    topics: Counter = field(default_factory=Counter)

    def line(self) -> str:
        if self.uncounted:
            held = ": an unknown number of messages lost"
        elif self.messages is None:
            held = ""
        else:
            held = f": {self.messages} message(s) lost" + (
                f" ({', '.join(f'{n} on {t}' for t, n in sorted(self.topics.items()))})"
                if self.topics
                else ""
            )
        return f"{self.where}: {self.what}{held}"


def one_line(text: str) -> str:
    """Text for one line of a report or a refusal: every run of whitespace, newlines too (in a
    parser's or a database's message), as one space."""
    return " ".join(text.split())


def error_text(e: BaseException) -> str:
    """`Type: message` of an exception, on one line."""
    return one_line(f"{type(e).__name__}: {e}")


def id_ranges(indexes: list[int]) -> str:
    """[1, 2, 3, 7] -> '1-3, 7'."""
    out, start = [], None
    for i, k in enumerate(indexes):
        if start is None:
            start = k
        if i + 1 == len(indexes) or indexes[i + 1] != k + 1:
            out.append(str(start) if start == k else f"{start}-{k}")
            start = None
    return ", ".join(out)


@dataclass
class ReadReport:
    """Everything the reader could not use, and why. Empty `losses` = the file was whole.

    `suspect`: scans that were read but cannot be vouched for (scan index -> why): their bytes
    had no CRC of their own in a file whose data-section CRC failed, or a loss before them held
    an unknown number of clouds, so their number may differ from the intact file's.
    """

    path: str = ""
    losses: list[Loss] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    messages: Counter = field(default_factory=Counter)  # topic -> messages recovered
    skipped: list[SkippedScan] = field(default_factory=list)
    suspect: dict[int, str] = field(default_factory=dict)
    unknown_labels: int = 0  # points whose label is unknown or invalid (-> 0)
    unknown_gt_labels: int = 0
    partial_chunk_messages: int = 0  # recovered from a chunk the file ends inside

    def lines(self) -> list[str]:
        out = [loss.line() for loss in self.losses] + list(self.notes)
        if self.partial_chunk_messages:
            out.append(
                f"{self.partial_chunk_messages} message(s) recovered from the incomplete "
                f"last chunk (its CRC cannot be checked; cut files keep their bytes)"
            )
        out += [s.line() for s in self.skipped]
        by_reason: dict[str, list[int]] = {}
        for index, why in sorted(self.suspect.items()):
            by_reason.setdefault(why, []).append(index)
        out += [
            f"scan(s) {id_ranges(ks)} mapped but suspect: {why}" for why, ks in by_reason.items()
        ]
        if self.unknown_labels:
            out.append(
                f"{self.unknown_labels} point(s) with an unknown label id (or an invalid "
                f"value) mapped to 0"
            )
        if self.unknown_gt_labels:
            out.append(
                f"{self.unknown_gt_labels} point(s) with an unknown ground-truth id (or "
                f"an invalid value) -> 0"
            )
        return out

    def to_dict(self) -> dict:
        return {
            "path": self.path,
            "damaged": bool(self.losses),
            "losses": [loss.line() for loss in self.losses],
            "notes": list(self.notes),
            "messages": dict(self.messages),
            "skipped_scans": [
                {"index": s.index, "name": s.name, "reason": s.reason} for s in self.skipped
            ],
            "suspect_scans": [
                {"index": k, "reason": why} for k, why in sorted(self.suspect.items())
            ],
            "unknown_labels": self.unknown_labels,
            "unknown_gt_labels": self.unknown_gt_labels,
            "partial_chunk_messages": self.partial_chunk_messages,
        }
