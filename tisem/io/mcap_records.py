"""The record layer of an MCAP file, damaged or not: Schema, Channel and Message records in the
order of the file's data, and a report of everything that could not be used.

The data section is the truth. It is read front to back on every pass, so a message's place in
the data fixes its number, and a damaged chunk index can neither duplicate nor skip a chunk.
The summary (when its CRC matches, or it has none) only helps: its schemas and channels
survive a lost chunk, its chunk index is compared with the data (a disagreement is reported),
finds the next chunk after a record whose length is damaged, and counts what a damaged stretch
held. Every CRC present is checked: each chunk's, the summary's, the data section's (in the
data-end record) and attachments'. A chunk that fails is skipped whole; what it held is counted
from the message index records after it in the data (or from its own records, when they still
parse); when that is impossible the loss says so, and the reader marks the scans after it.
A file cut short gives every message that was completely written.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from pathlib import Path

from mcap.records import Channel, ChunkIndex, Schema

from tisem.errors import DatasetError
from tisem.io.mcap_items import LostMessages, McapMessage
from tisem.io.mcap_report import Loss, ReadReport, lost_on
from tisem.io.mcap_summary import MAGIC, crc_of_range, read_footer, read_summary
from tisem.io.mcap_walk import Walk

__all__ = ["McapRecords", "McapMessage", "LostMessages", "Loss", "ReadReport", "MAGIC"]


class McapRecords:
    """Schema, Channel and Message records of an MCAP file, in data order, surviving damage.

    After a pass, `data_crc` is "match", "mismatch" or "absent" (None before, or when the
    data section has no data-end record to check), and `excess` counts, per topic, messages
    beyond what the summary's statistics record (damaged records taken for messages).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        try:
            self.size = Path(path).stat().st_size
        except OSError as e:
            raise DatasetError(f"{path}: cannot open ({e.strerror})") from None
        if self.size == 0:
            raise DatasetError(f"{path}: the file is empty")
        with open(path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise DatasetError(
                    f"{path}: not an MCAP file (it does not start with the MCAP magic bytes)"
                )
            self.footer = read_footer(f, self.size)
            self.summary, self.summary_problem = (
                read_summary(f, self.footer) if self.footer else (None, None)
            )
        # where the data ends: the summary's start (when it is used), the footer, the file's end
        self.limit = (
            self.summary.start if self.summary else self.footer.offset if self.footer else self.size
        )
        self.index: dict[int, list[ChunkIndex]] = {}  # offset -> entries
        for entry in self.summary.chunk_indexes if self.summary else ():
            self.index.setdefault(entry.chunk_start_offset, []).append(entry)
        self.data_crc: str | None = None
        self.excess = Counter()  # topic -> messages beyond the summary's counts

    def records(
        self, report: ReadReport
    ) -> Iterator[Schema | Channel | McapMessage | LostMessages]:
        """Yield Schema, Channel, McapMessage and LostMessages records in data order; count
        messages per topic and append what was dropped or distrusted to `report`."""
        self._notes(report)
        with open(self.path, "rb") as f:
            walk = Walk(self, f, report)
            if self.summary is not None:  # they survive a lost chunk
                yield from self.summary.schemas.values()
                yield from self.summary.channels.values()
            orphans = Counter()
            for rec in walk.run():
                if isinstance(rec, McapMessage):
                    ch = walk.channels.get(rec.channel_id)
                    if ch is None:
                        orphans[rec.channel_id] += 1
                        if not rec.crc_checked:
                            # no CRC vouches for its id: a cloud whose id the damage changed
                            # reads so too, and the scans after it would be renumbered
                            yield LostMessages(
                                rec.channel_id,
                                1,
                                f"message at log time {rec.log_time * 1e-9:.3f} s",
                                guessed=True,
                            )
                        continue
                    report.messages[ch.topic] += 1
                yield rec
        walk.finish()
        self._check_data_crc(report, walk)
        for cid, n in orphans.items():
            report.losses.append(
                Loss(
                    lost_on(None, cid),
                    "no Channel record names its id (its record was lost, or the damage "
                    "changed the id), so its messages cannot be decoded",
                    messages=n,
                    topics=Counter({lost_on(None, cid): n}),
                )
            )
        self._check_counts(report)

    def _check_data_crc(self, report: ReadReport, walk: Walk) -> None:
        """The data section's CRC, from the data-end record the footer leads to (the walk may
        not have reached it), once per file."""
        footer = self.footer
        if self.data_crc is None and footer is not None and footer.data_end_at is not None:
            if footer.data_end_crc == 0:
                self.data_crc = "absent"
            else:
                with open(self.path, "rb") as f:
                    crc = crc_of_range(f, 0, footer.data_end_at)
                self.data_crc = "match" if crc == footer.data_end_crc else "mismatch"
        if self.data_crc == "mismatch":
            report.losses.append(Loss("data section", walk.ledger.data_crc_mismatch()))

    def _notes(self, report: ReadReport) -> None:
        if self.footer is None:
            report.notes.append(
                "no summary section (the file does not end with a footer: cut "
                "short, or its end is damaged): the file was read linearly"
            )
        elif self.footer.summary_start == 0:
            report.notes.append(
                "no summary section (written without one): the file was read linearly"
            )
        elif self.summary_problem is not None:
            report.losses.append(
                Loss(
                    "summary section",
                    f"{self.summary_problem}; it was not used and the file was read from its data",
                )
            )
        elif not self.summary.chunk_indexes:
            report.notes.append("no chunk index: the file was read linearly")

    def _check_counts(self, report: ReadReport) -> None:
        """With a summary, compare what was read with the recorded message counts: fewer is
        a loss nothing else explained, more means damaged records were taken for messages."""
        stats = self.summary.statistics if self.summary else None
        if stats is None:
            return
        counted = Counter()
        for cid, n in stats.channel_message_counts.items():
            ch = self.summary.channels.get(cid)
            counted[lost_on(ch, cid)] += n
        missing = counted - report.messages
        accounted = Counter()
        for loss in report.losses:
            accounted.update(loss.topics)
        unaccounted = missing - accounted
        if unaccounted:
            report.losses.append(
                Loss(
                    "summary statistics",
                    "messages counted in the summary were not found",
                    messages=sum(unaccounted.values()),
                    topics=unaccounted,
                )
            )
        self.excess = report.messages - counted if counted else Counter()
        if self.excess:
            extra = ", ".join(f"{n} on {t}" for t, n in sorted(self.excess.items()))
            report.losses.append(
                Loss(
                    "summary statistics",
                    f"the data holds more messages "
                    f"than the summary counts ({extra}): records outside "
                    f"CRC-checked chunks were damaged into messages",
                )
            )
