"""Labelled LiDAR scans from an MCAP recording, damaged or not.

`McapScanReader` reads the file twice, through its record layer (`tisem.io.mcap_records`,
which survives damage and reports what was lost):
- a survey pass (`tisem.io.mcap_survey`) decodes only pose messages (/tf, /tf_static,
  `--pose-topic`), counts messages, picks the cloud topic and checks that a cloud has the
  fields and frame the options need, so every "this cannot work" error comes before any
  mapping (with the damage that may be why);
- the second pass decodes clouds one at a time and yields `Scan`s with the pose looked up at
  the header stamp from the full transform buffer (exactly what tf2 gives offline). A scan
  that cannot be used (a lost message, a layout that disagrees with its data, no points, no
  pose) becomes a `SkippedScan` with the reason. A scan read from bytes that nothing vouches
  for in a file known to be damaged, or posed across lost /tf messages, is marked in
  `report.suspect`; labels that are no labels count as unknown (0, no evidence).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from mcap.records import Channel

from tisem.errors import ScanError, SkippedScan
from tisem.io import pointcloud2 as pc2
from tisem.io.mcap_messages import (
    MessageDecoders,
    cloud_labels,
    cloud_parts,
    cloud_probabilities,
)
from tisem.io.mcap_options import McapOptions
from tisem.io.mcap_records import LostMessages, McapMessage, McapRecords, ReadReport
from tisem.io.mcap_report import error_text
from tisem.io.mcap_survey import Survey
from tisem.io.stamps import split_ns
from tisem.io.tf import TfError
from tisem.labels import TrainIdNotes
from tisem.scan import McapSource, Scan, finite_rows

__all__ = ["McapOptions", "McapScanReader"]

log = logging.getLogger(__name__)


class McapScanReader:
    """Scans from an MCAP log: iterate for `Scan | SkippedScan`, in message order.

    Construction surveys the file (raises `DatasetError` with a clear message when nothing can
    be mapped: no cloud topic, an ambiguous one, a missing label field, no transform path).
    Afterwards: `topic`, `frame_id`, `total` (scans that will be yielded), `tf` (the buffer),
    `report` (damage found while surveying; skipped scans and unknown labels are added while
    iterating).
    """

    def __init__(
        self,
        path: str | Path,
        options: McapOptions | None = None,
        *,
        records: McapRecords | None = None,
        decoders: MessageDecoders | None = None,
    ) -> None:
        """`records` and `decoders` replace the MCAP file's (`tisem.io.bag_open`: split files,
        bags that `rosbags` reads); they default to those of the file at `path`."""
        self.options = options or McapOptions()
        self.options.validate()
        self.path = str(path)
        self.report = ReadReport(path=self.path)
        self._records = records if records is not None else McapRecords(path)
        self._decoders = decoders if decoders is not None else MessageDecoders()
        self._unknown: dict[int, tuple[int, int]] = {}  # scan index -> unknown labels, gt
        self.train_ids = TrainIdNotes(log)  # label_space "auto" reading train ids
        survey = Survey(self.path, self.options, self._records, self._decoders, self.report)
        self.topic, self.frame_id = survey.topic, survey.frame_id
        self.tf, self.total = survey.tf, survey.total
        self._schemas, self._channels, self._kinds = survey.schemas, survey.channels, survey.kinds
        self._poses_lost = survey.poses_lost
        self._unvouched_mount = survey.unvouched_mount
        self._label_spaces = survey.label_spaces

    @property
    def reading_notes(self) -> list[str]:
        """How the labels were read where the options left it open (label fields found to hold
        train ids), for the run's record."""
        return list(self.train_ids.lines)

    @property
    def records(self):
        """The record source the scans are read from (the file's, or the bag's)."""
        return self._records

    # -- pass 2: the scans
    def __len__(self) -> int:
        return self.total

    def __iter__(self) -> Iterator[Scan | SkippedScan]:
        scratch = ReadReport()  # damage was reported by the survey already
        index = -1
        targets = set()  # channel ids of the topic (usually one)
        named = set()  # channel ids whose Channel record has come
        renumbered = None  # what before may have changed the numbering
        for rec in self._records.records(scratch):
            if isinstance(rec, Channel):
                named.add(rec.id)
                if rec.topic == self.topic:
                    targets.add(rec.id)
                continue
            if isinstance(rec, LostMessages):
                if rec.channel_id is None:
                    renumbered = (
                        renumbered or f"{rec.where}, holding an unknown number of messages,"
                    )
                elif rec.channel_id not in named:
                    # on a channel no record has named (yet): clouds, maybe
                    renumbered = renumbered or (
                        f"{rec.where}, a loss on a channel no record names (clouds, maybe),"
                    )
                elif rec.guessed:  # a flipped channel id may have put a cloud on another topic
                    renumbered = renumbered or (
                        f"{rec.where}, whose messages were counted from its damaged bytes,"
                    )
                if rec.channel_id in targets:
                    # keep the intact file's numbering: a lost cloud is a skipped scan
                    for _ in range(rec.count):
                        index += 1
                        if self._selected(index):
                            yield self._skip(
                                SkippedScan(
                                    index,
                                    f"{self.topic}#{index}",
                                    f"message lost in a damaged {rec.where}",
                                )
                            )
                        if self._past_last(index):
                            return
                continue
            if not isinstance(rec, McapMessage) or rec.channel_id not in targets:
                continue
            if not rec.crc_checked and self._records.excess[self.topic]:
                renumbered = renumbered or (
                    f"a message outside CRC-checked chunks (the data "
                    f"holds more on {self.topic} than the summary counts)"
                )
            index += 1
            if self._selected(index):
                item = self._skip(self._scan(index, rec))
                if isinstance(item, Scan):
                    self._mark_suspect(item, rec, renumbered)
                yield item
            if self._past_last(index):
                return  # the survey has reported the rest: a chunk of a long log stops here

    def _mark_suspect(self, scan: Scan, rec: McapMessage, renumbered: str | None) -> None:
        """Scans read from bytes nothing vouches for in a file known to be damaged, or posed
        across where pose messages were lost."""
        index = scan.index
        gap = None
        if self._poses_lost and scan.source.frame_id.lstrip("/") != self.options.map_frame.lstrip(
            "/"
        ):
            gap = self.tf.interpolation_gap(
                self.options.map_frame, scan.source.frame_id, scan.source.stamp_ns
            )
        if gap is not None:
            self.report.suspect[index] = (
                f"pose messages were lost and its pose is interpolated across the gap: {gap}"
            )
        elif renumbered is not None:
            self.report.suspect[index] = (
                f"{renumbered} came before it, so its number may differ from the intact file's"
            )
        elif self._unvouched_mount is not None:
            self.report.suspect[index] = self._unvouched_mount
        elif not rec.crc_checked and self._records.data_crc == "mismatch":
            self.report.suspect[index] = (
                "the data section's CRC does not match and no CRC of its own covers this cloud"
            )

    def _selected(self, index: int) -> bool:
        return index >= self.options.first and (
            self.options.last is None or index <= self.options.last
        )

    def _past_last(self, index: int) -> bool:
        return self.options.last is not None and index >= self.options.last

    def _skip(self, item: Scan | SkippedScan) -> Scan | SkippedScan:
        """Record a skipped scan once (the pipeline may read the log twice) and pass it on."""
        if isinstance(item, SkippedScan) and all(
            s.index != item.index for s in self.report.skipped
        ):
            self.report.skipped.append(item)
        return item

    def _scan(self, index: int, rec: McapMessage) -> Scan | SkippedScan:
        opts = self.options
        ch = self._channels[rec.channel_id]
        name = f"{self.topic}#{index} (log time {rec.log_time / 1e9:.6f} s)"
        try:
            msg = self._decoders.decode(ch, self._schemas.get(ch.schema_id), rec.data)
            arr, frame_id, stamp_ns, T_frame_cloud = cloud_parts(self._kinds[self.topic], msg)
            sec, nsec = split_ns(stamp_ns)
            name = f"{self.topic}@{sec}.{nsec:09d}"
            used = ["x", "y", "z", opts.prob_field or opts.label_field] + (
                [opts.gt_field] if opts.gt_field else []
            )
            pc2.check_used_fields(arr, used)
            if not frame_id:
                raise pc2.CloudFormatError("the cloud has an empty frame_id")
            points = pc2.xyz(arr)
            if len(points) == 0:
                raise pc2.CloudFormatError("the cloud has 0 points")
            if not finite_rows(points).any():
                raise pc2.CloudFormatError(f"all {len(points)} points are non-finite (NaN/inf)")
            T = (
                np.eye(4)
                if frame_id.lstrip("/") == opts.map_frame.lstrip("/")
                else self.tf.lookup(opts.map_frame, frame_id, stamp_ns)
            )
            if T_frame_cloud is not None:
                T = T @ T_frame_cloud
            labels = probs = gt = None
            unknown = unknown_gt = 0
            if opts.prob_field:
                probs, unknown = cloud_probabilities(arr, opts.prob_field, opts.num_classes)
            else:
                labels, unknown = self._labels(arr, opts.label_field, "labels", name)
            if opts.gt_field:
                gt, unknown_gt = self._labels(arr, opts.gt_field, "ground truth", name)
            self._count_unknown(index, unknown, unknown_gt)
            return Scan(
                points_sensor=points,
                T_world_sensor=T,
                stamp_s=stamp_ns / 1e9,
                labels=labels,
                probs=probs,
                gt_labels=gt,
                index=index,
                name=name,
                source=McapSource(
                    unknown_raw_ids=unknown,
                    unknown_gt_ids=unknown_gt,
                    topic=self.topic,
                    frame_id=frame_id,
                    stamp_ns=stamp_ns,
                    log_time_ns=rec.log_time,
                ),
            )
        except (TfError, pc2.CloudFormatError, ScanError) as e:
            return SkippedScan(index, name, str(e))
        except Exception as e:  # noqa: BLE001 - undecodable bytes raise anything
            return SkippedScan(index, name, f"cannot decode the message ({error_text(e)})")

    def _labels(self, arr, field: str, source: str, name: str) -> tuple:
        """(train ids, unknown count) of a cloud's label field of `source` ("labels" or
        "ground truth"), values that fit both spaces read in the space of the recording's first
        cloud whose field fits one (raw where none does: the survey found it), whatever part
        of the recording is read."""
        opts = self.options
        either = self._label_spaces.get((self.topic, field), "raw")
        labels, unknown, space = cloud_labels(
            arr, field, opts.label_space, opts.num_classes, either
        )
        self.train_ids.read(source, f"{name} field {field!r}", space)
        return labels, unknown

    def _count_unknown(self, index: int, unknown: int, unknown_gt: int) -> None:
        """Per scan, so that reading the log twice (the final pass) does not count twice."""
        self._unknown[index] = (unknown, unknown_gt)
        self.report.unknown_labels = sum(u for u, _ in self._unknown.values())
        self.report.unknown_gt_labels = sum(g for _, g in self._unknown.values())
