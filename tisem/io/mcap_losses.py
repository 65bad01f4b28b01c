"""The books of a walk over MCAP data: how many messages each loss held, on which topics, and
what no CRC vouched for.

Apart from the walk (`tisem.io.mcap_walk`), which finds the records, because this bookkeeping
spans records: a skipped chunk is counted from the message index records that follow it, so
its loss stays open until a record that is not one; and whether the CRCs covered every
message is known only at the end.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

from mcap.records import Channel

from tisem.io.mcap_items import LostMessages
from tisem.io.mcap_report import Loss, ReadReport, lost_on
from tisem.io.mcap_summary import Malformed, parse_message_index


@dataclass
class _Pending:
    """A loss (a skipped chunk) whose count waits for the message index records after it."""

    loss: Loss
    from_records: Counter | None  # what its damaged records still show
    from_index: Counter | None = None  # what the message index records after it say
    index_damaged: bool = False


class Ledger:
    """What the walk lost, counted into `report`, and what its CRCs could not cover.

    `channels` is the walk's own table (by id, filled as Channel records are read), so that
    a count names the topics known by then.
    """

    def __init__(self, report: ReadReport, channels: dict[int, Channel]) -> None:
        self.report, self.channels = report, channels
        self.pending: _Pending | None = None
        self.no_crc = 0  # chunks without a CRC
        self.outside = 0  # messages outside chunks

    def count_from_index(self, loss: Loss, from_records: Counter | None = None) -> None:
        """`loss` held what the message index records after it count; where they cannot,
        what `from_records` (its damaged records) shows, else an unknown number."""
        self.pending = _Pending(loss, from_records)

    def message_index(self, content: bytes) -> None:
        """A message index record outside chunks: it counts what the pending loss held."""
        if self.pending is None:
            return
        try:
            channel_id, n = parse_message_index(content)
        except Malformed:
            self.pending.index_damaged = True
            return
        self.pending.from_index = self.pending.from_index or Counter()
        self.pending.from_index[channel_id] += n

    def settle(self) -> Iterator[LostMessages]:
        """Count what the pending loss held, now that its message index records (if any)
        have been read."""
        lost, self.pending = self.pending, None
        if lost is None:
            return
        counts = lost.from_index if not lost.index_damaged else None
        guessed = False
        if counts is None and lost.from_records:  # (a chunk showing no message: unknown)
            counts, guessed = lost.from_records, True
            lost.loss.what += " (counted from its damaged records)"
        yield from self.account(lost.loss, counts, guessed)

    def account(
        self, loss: Loss, counts: Counter | None, guessed: bool = False
    ) -> Iterator[LostMessages]:
        """`loss` held `counts` messages per channel id (None: unknown; `guessed`: counted
        from damaged bytes): on the loss, and yielded for the readers' numbering."""
        if counts is None:
            loss.uncounted = True
            yield LostMessages(None, None, loss.where)
            return
        loss.messages = sum(counts.values())
        for channel_id, n in sorted(counts.items()):
            loss.topics[lost_on(self.channels.get(channel_id), channel_id)] += n
            if n:
                yield LostMessages(channel_id, n, loss.where, guessed)

    def data_crc_mismatch(self) -> str:
        """What a data-section CRC that does not match means for this file's messages."""
        return "its CRC (in the data-end record) does not match: some bytes are corrupted" + (
            "; every message lies in a chunk whose own CRC matched, so none is affected"
            if self.outside == 0 and self.no_crc == 0
            else "; messages without a CRC of their own cannot be told apart from damaged "
            "ones (their scans are marked suspect)"
        )

    def note_unchecked(self, data_crc: str | None) -> None:
        """After the walk: notes on what no CRC covered (`data_crc`: the data section's)."""
        if self.no_crc:
            self.report.notes.append(
                f"{self.no_crc} chunk(s) carry no CRC (rosbag2's default): "
                f"corrupted bytes inside them cannot be detected"
            )
        if self.outside and data_crc == "absent":
            self.report.notes.append(
                f"{self.outside} message(s) lie outside chunks and the "
                f"data section carries no CRC: corrupted bytes in them "
                f"cannot be detected"
            )
