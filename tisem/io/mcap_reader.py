"""Labelled LiDAR scans from an MCAP recording, damaged or not.

`McapScanReader` reads the file twice, through its record layer (`tisem.io.mcap_records`,
which survives damage and reports what was lost):
- a survey pass decodes only pose messages (/tf, /tf_static, `--pose-topic`), counts messages,
  picks the cloud topic and checks that a cloud has the fields and frame the options need, so
  every "this cannot work" error comes before any mapping (with the damage that may be why);
- the second pass decodes clouds one at a time and yields `Scan`s with the pose looked up at
  the header stamp from the full transform buffer (exactly what tf2 gives offline). A scan
  that cannot be used (a lost message, a layout that disagrees with its data, no points, no
  pose) becomes a `SkippedScan` with the reason. A scan read from bytes that nothing vouches
  for in a file known to be damaged, or posed across lost /tf messages, is marked in
  `report.suspect`; labels that are no labels count as unknown (0, no evidence).
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.records import Channel, Schema

from tisem.errors import DatasetError, ScanError, SkippedScan
from tisem.io import pointcloud2 as pc2
from tisem.io.mcap_messages import (
    CLOUD_SCHEMAS,
    POSE_SCHEMAS,
    TF_SCHEMAS,
    UNSUPPORTED_CLOUDS,
    MessageDecoders,
    cloud_labels,
    cloud_parts,
    cloud_probabilities,
    pose_edges,
)
from tisem.io.mcap_records import Loss, LostMessages, McapMessage, McapRecords, ReadReport
from tisem.io.stamps import split_ns
from tisem.io.tf import TfBuffer, TfError
from tisem.labels import NUM_CLASSES
from tisem.scan import McapSource, Scan, finite_rows

log = logging.getLogger(__name__)


@dataclass
class McapOptions:
    """How to turn a recording into scans (the `map_mcap.py` options)."""

    topic: str | None = None  # the cloud topic; found automatically when there is one
    label_field: str = "label"  # per-point label field ...
    label_space: str = "raw"  # ... holding raw SemanticKITTI ids or train ids
    prob_field: str | None = None  # or a count=C float field of class probabilities
    gt_field: str | None = None  # ground-truth label field (same label space), for metrics
    map_frame: str = "map"
    pose_topic: str | None = None  # Odometry / PoseStamped instead of /tf (dynamic)
    pose_child_frame: str | None = None  # the frame a PoseStamped is the pose of (default: the
    # top of the cloud frame's /tf_static chain)
    tf_tolerance_s: float = 0.0  # allowed extrapolation beyond a transform's samples
    first: int = 0  # scans by message order, last inclusive
    last: int | None = None
    num_classes: int = NUM_CLASSES

    def validate(self) -> None:
        """ValueError naming the option, its value and what is allowed."""
        if self.label_space not in ("raw", "train"):
            raise ValueError(f"label_space must be 'raw' or 'train', got {self.label_space!r}")
        tolerance = self.tf_tolerance_s
        if not (isinstance(tolerance, (int, float)) and 0 <= tolerance < math.inf):
            raise ValueError(f"tf_tolerance_s must be a finite number >= 0, got {tolerance!r}")
        for name in ("label_field", "map_frame"):
            if not (isinstance(getattr(self, name), str) and getattr(self, name)):
                raise ValueError(f"{name} must be a non-empty string, got {getattr(self, name)!r}")
        if not (_is_int(self.first) and self.first >= 0):
            raise ValueError(f"first must be a whole number >= 0, got {self.first!r}")
        if self.last is not None and not (_is_int(self.last) and self.last >= self.first):
            raise ValueError(
                f"last must be a whole number >= first ({self.first}) or None, got {self.last!r}"
            )
        if not (_is_int(self.num_classes) and self.num_classes >= 2):
            raise ValueError(f"num_classes must be a whole number >= 2, got {self.num_classes!r}")


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _describe_topics(counts: Counter, kinds: dict) -> str:
    return ", ".join(f"{t} ({kinds.get(t, '?')}, {n} msgs)" for t, n in sorted(counts.items()))


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
        self._survey()

    # -- pass 1
    def _survey(self) -> None:
        opts = self.options
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        kinds: dict[str, str] = {}  # topic -> schema name
        samples = []  # (static, foxglove, parent, child, t, xyz, q)
        first_cloud: dict[str, object] = {}  # topic -> first usable cloud
        misfits: dict[str, object] = {}  # topic -> first cloud lacking a field
        self._cloud_errors: dict[str, str] = {}  # topic -> why its first bad cloud failed
        undecodable = Counter()
        pose_errors: dict[str, str] = {}
        lost_clouds = Counter()  # channel id -> messages in lost chunks
        for rec in self._records.records(self.report):
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
                continue
            if isinstance(rec, Channel):
                channels[rec.id] = rec
                schema = schemas.get(rec.schema_id)
                kinds[rec.topic] = (
                    schema.name if schema else "unknown schema" if rec.schema_id else "no schema"
                )
                continue
            if isinstance(rec, LostMessages):
                if rec.channel_id is not None:
                    lost_clouds[rec.channel_id] += rec.count
                continue
            ch = channels[rec.channel_id]
            name = kinds[ch.topic]
            # with --pose-topic, /tf is ignored but /tf_static still gives the sensor mount
            static = ch.topic.endswith("tf_static")
            is_pose = (
                name in TF_SCHEMAS
                and (opts.pose_topic is None or static)
                or ch.topic == opts.pose_topic
            )
            wants_cloud = (
                name in CLOUD_SCHEMAS
                and ch.topic not in first_cloud
                and (opts.topic is None or ch.topic == opts.topic)
            )
            if not (is_pose or wants_cloud):
                continue
            try:
                msg = self._decoders.decode(ch, schemas.get(ch.schema_id), rec.data)
                if wants_cloud:
                    parts = cloud_parts(name, msg)
                    if self._cloud_problem(parts, ch.topic) is None:
                        first_cloud[ch.topic] = parts
                    else:  # one odd cloud must not refuse the file
                        misfits.setdefault(ch.topic, parts)
                    continue
                edges = pose_edges(name, msg, default_parent=opts.map_frame, default_child=None)
            # a damaged message (in a chunk without CRC) or a schema we cannot parse; a bad
            # cloud is skipped with its reason when the scans are read, so only its reason is
            # kept here
            except Exception as e:  # noqa: BLE001 - decoders raise anything on bad bytes
                why = f"{type(e).__name__}: {e}"
                if wants_cloud:
                    self._cloud_errors.setdefault(ch.topic, why)
                else:
                    undecodable[ch.topic] += 1
                    pose_errors.setdefault(ch.topic, why)
                continue
            fox = name.startswith("foxglove.")
            samples += [(static, fox, *e) for e in edges]
        for topic, n in undecodable.items():
            self.report.losses.append(
                Loss(
                    topic,
                    f"messages could not be decoded (the first: {pose_errors[topic][:200]})",
                    messages=n,
                    topics=Counter({topic: n}),
                )
            )
        pose_topics = {t for t, k in kinds.items() if k in TF_SCHEMAS or t == opts.pose_topic}
        # a lost pose message changes the poses interpolated across where it was
        self._poses_lost = bool(undecodable) or any(
            loss.uncounted or pose_topics & set(loss.topics) for loss in self.report.losses
        )
        self._kinds = kinds
        self._schemas, self._channels = schemas, channels
        try:
            self.topic = self._pick_topic(kinds, {*first_cloud, *misfits})
            if self.topic not in first_cloud:  # no cloud has what the options need
                raise DatasetError(self._cloud_problem(misfits[self.topic], self.topic))
            self.frame_id = first_cloud[self.topic][1]
            self._build_tf(samples)
            self._check_tf()
        except DatasetError as e:  # what was lost may be why
            raise DatasetError(f"{e}{self._damage()}") from None
        n = self.report.messages[self.topic] + sum(
            k
            for cid, k in lost_clouds.items()
            if cid in channels and channels[cid].topic == self.topic
        )
        last = n - 1 if opts.last is None else min(opts.last, n - 1)
        self.total = max(0, last - opts.first + 1)

    def _pick_topic(self, kinds: dict, decoded: set) -> str:
        counts = Counter({t: self.report.messages[t] for t in kinds})
        clouds = {t for t, k in kinds.items() if k in CLOUD_SCHEMAS and counts[t] > 0}
        where = f"{self.path}"

        def listing(topics) -> str:
            return _describe_topics(Counter({c: counts[c] for c in topics}), kinds) or "none"

        if self.options.topic is not None:
            t = self.options.topic
            if t not in kinds:
                raise DatasetError(
                    f"{where}: no topic {t!r}; point-cloud topics: {listing(clouds)}"
                )
            if kinds[t] not in CLOUD_SCHEMAS:
                raise DatasetError(
                    f"{where}: topic {t!r} carries {kinds[t]}, not a point cloud "
                    f"tisem reads ({', '.join(CLOUD_SCHEMAS)})"
                )
            clouds = {t}
        if not clouds:
            other = [t for t, k in kinds.items() if k in UNSUPPORTED_CLOUDS]
            hint = (
                f"; {', '.join(f'{t} ({kinds[t]})' for t in other)} cannot be read "
                f"(supported: {', '.join(CLOUD_SCHEMAS)})"
                if other
                else ""
            )
            raise DatasetError(
                f"{where}: no point-cloud messages found{hint}; topics: "
                f"{_describe_topics(counts, kinds) or 'none'}"
            )
        if len(clouds) > 1:
            raise DatasetError(
                f"{where}: several point-cloud topics, choose one with --topic: {listing(clouds)}"
            )
        topic = clouds.pop()
        if topic not in decoded:
            why = self._cloud_errors.get(topic, "unknown")
            raise DatasetError(
                f"{where}: none of the {counts[topic]} messages on {topic} "
                f"could be decoded (the first: {why[:300]})"
            )
        return topic

    def _damage(self) -> str:
        """'; the file is damaged: ...' (the first few losses), or '' for a whole file."""
        losses = [loss.line() for loss in self.report.losses]
        if not losses:
            return ""
        more = f"; and {len(losses) - 3} more" if len(losses) > 3 else ""
        return f"; the file is damaged: {'; '.join(losses[:3])}{more}"

    def _cloud_problem(self, parts, topic: str) -> str | None:
        """Why a decoded cloud lacks what the options need (fields, a frame), or None. Missing
        fields are a property of the recording: said before mapping anything."""
        arr, frame_id, _, _ = parts
        opts = self.options
        needed = ["x", "y", "z", opts.prob_field or opts.label_field]
        if opts.gt_field:
            needed.append(opts.gt_field)
        missing = [f for f in needed if not pc2.has_field(arr, f)]
        if missing:
            what = {
                opts.label_field: "label field (--label-field)",
                opts.prob_field: "probability field (--prob-field)",
                opts.gt_field: "ground-truth field (--gt-field)",
            }
            return (
                f"{self.path}: the clouds on {topic} have no "
                f"{' and no '.join(repr(f) + ' ' + what.get(f, 'field') for f in missing)}; "
                f"their fields are: {pc2.describe_fields(arr)}"
            )
        if not frame_id:
            return f"{self.path}: the clouds on {topic} have an empty frame_id"
        return None

    def _build_tf(self, samples: list) -> None:
        opts = self.options
        self.tf = TfBuffer(max_extrapolation_s=opts.tf_tolerance_s)
        for static, _fox, parent, child, t, xyz, q in samples:
            if static:
                self.tf.add(parent, child, t, xyz, q, static=True)
        # a PoseStamped names no child: by default it is the pose of the top of the sensor's
        # static mount (base_link for base_link -> velodyne), or of the sensor when unmounted
        child_default = opts.pose_child_frame or self.tf.root_of(self.frame_id)
        fox_children = set()
        for static, fox, parent, child, t, xyz, q in samples:
            if static:
                continue
            self.tf.add(parent, child or child_default, t, xyz, q)
            if fox:
                fox_children.add((child or child_default).lstrip("/"))
        if fox_children:
            promoted = self.tf.promote_constant_edges(fox_children)
            if promoted:
                self.report.notes.append(
                    f"foxglove transforms that never change were taken as "
                    f"static: {', '.join(sorted(promoted))}"
                )
        self.report.notes += [f"tf: {w}" for w in self.tf.warnings]

    def _check_tf(self) -> None:
        opts = self.options
        if opts.pose_topic is not None and opts.pose_topic not in self._kinds:
            raise DatasetError(
                f"{self.path}: no topic {opts.pose_topic!r}; topics: "
                f"{_describe_topics(self.report.messages, self._kinds)}"
            )
        if opts.pose_topic is not None and self._kinds[opts.pose_topic] not in POSE_SCHEMAS:
            raise DatasetError(
                f"{self.path}: --pose-topic {opts.pose_topic} carries "
                f"{self._kinds[opts.pose_topic]}; supported: "
                f"{', '.join(POSE_SCHEMAS)}"
            )
        if self.frame_id.lstrip("/") == opts.map_frame.lstrip("/"):
            return
        if not self.tf.can_connect(opts.map_frame, self.frame_id):
            try:
                self.tf.lookup(opts.map_frame, self.frame_id, 0)
            except TfError as e:
                raise DatasetError(
                    f"{self.path}: no transform from the map frame "
                    f"{opts.map_frame!r} to the cloud frame {self.frame_id!r} "
                    f"(--map-frame, --pose-topic): {e}"
                ) from None

    # -- pass 2
    def __len__(self) -> int:
        return self.total

    def __iter__(self) -> Iterator[Scan | SkippedScan]:
        scratch = ReadReport()  # damage was reported by the survey already
        index = -1
        targets = set()  # channel ids of the topic (usually one)
        renumbered = None  # what before may have changed the numbering
        for rec in self._records.records(scratch):
            if isinstance(rec, Channel):
                if rec.topic == self.topic:
                    targets.add(rec.id)
                continue
            if isinstance(rec, LostMessages) and rec.channel_id is None:
                renumbered = renumbered or f"{rec.where}, holding an unknown number of messages,"
                continue
            if isinstance(rec, LostMessages) and rec.channel_id in targets:
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
        elif not rec.crc_checked and self._records.data_crc == "mismatch":
            self.report.suspect[index] = (
                "the data section's CRC does not match and no CRC of its own covers this cloud"
            )

    def _selected(self, index: int) -> bool:
        return index >= self.options.first and (
            self.options.last is None or index <= self.options.last
        )

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
                labels, unknown = cloud_labels(
                    arr, opts.label_field, opts.label_space, opts.num_classes
                )
            if opts.gt_field:
                gt, unknown_gt = cloud_labels(
                    arr, opts.gt_field, opts.label_space, opts.num_classes
                )
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
            return SkippedScan(index, name, f"cannot decode the message ({type(e).__name__}: {e})")

    def _count_unknown(self, index: int, unknown: int, unknown_gt: int) -> None:
        """Per scan, so that reading the log twice (the final pass) does not count twice."""
        self._unknown[index] = (unknown, unknown_gt)
        self.report.unknown_labels = sum(u for u, _ in self._unknown.values())
        self.report.unknown_gt_labels = sum(g for _, g in self._unknown.values())
