"""Labelled LiDAR scans from an MCAP recording, damaged or not.

`McapScanReader` reads the file twice, through its record layer (`tisem.io.mcap_records`,
which survives damage and reports what was lost):
- a survey pass decodes only pose messages (/tf, /tf_static, `--pose-topic`), counts messages,
  picks the cloud topic and checks the first cloud's fields and frame, so every "this cannot
  work" error comes before any mapping;
- the second pass decodes clouds one at a time and yields `Scan`s with the pose looked up at
  the header stamp from the full transform buffer (exactly what tf2 gives offline). A scan
  that cannot be used becomes a `SkippedScan` with the reason.
"""
from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
from mcap.records import Channel, Message, Schema

from tisem.errors import DatasetError, ScanError, SkippedScan
from tisem.io import pointcloud2 as pc2
from tisem.io.mcap_messages import (CLOUD_SCHEMAS, POSE_SCHEMAS, TF_SCHEMAS, UNSUPPORTED_CLOUDS,
                                    MessageDecoders, cloud_parts, pose_edges)
from tisem.io.mcap_records import Loss, LostMessages, McapRecords, ReadReport
from tisem.io.stamps import split_ns
from tisem.io.tf import TfBuffer, TfError
from tisem.labels import NUM_CLASSES, raw_to_train
from tisem.scan import McapSource, Scan

log = logging.getLogger(__name__)


@dataclass
class McapOptions:
    """How to turn a recording into scans (the `map_mcap.py` options)."""

    topic: str | None = None            # the cloud topic; found automatically when there is one
    label_field: str = "label"          # per-point label field ...
    label_space: str = "raw"            # ... holding raw SemanticKITTI ids or train ids
    prob_field: str | None = None       # or a count=C float field of class probabilities
    gt_field: str | None = None         # ground-truth label field (same label space), for metrics
    map_frame: str = "map"
    pose_topic: str | None = None       # Odometry / PoseStamped instead of /tf (dynamic)
    pose_child_frame: str | None = None # the frame a PoseStamped is the pose of (default: the
                                        # top of the cloud frame's /tf_static chain)
    tf_tolerance_s: float = 0.0         # allowed extrapolation beyond a transform's samples
    first: int = 0                      # scans by message order, last inclusive
    last: int | None = None
    num_classes: int = NUM_CLASSES

    def validate(self) -> None:
        if self.label_space not in ("raw", "train"):
            raise ValueError(f"label_space must be 'raw' or 'train', got {self.label_space!r}")
        if self.tf_tolerance_s < 0:
            raise ValueError("tf_tolerance_s must be >= 0")


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

    def __init__(self, path: str | Path, options: McapOptions | None = None) -> None:
        self.options = options or McapOptions()
        self.options.validate()
        self.path = str(path)
        self.report = ReadReport(path=self.path)
        self._records = McapRecords(path)
        self._decoders = MessageDecoders()
        self._survey()

    # -- pass 1
    def _survey(self) -> None:
        opts = self.options
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        kinds: dict[str, str] = {}                    # topic -> schema name
        samples = []                                  # (static, foxglove, parent, child, t, xyz, q)
        first_cloud: dict[str, object] = {}           # topic -> first decodable cloud
        undecodable = Counter()
        lost_clouds = Counter()                       # channel id -> messages in lost chunks
        for rec in self._records.records(self.report):
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
                continue
            if isinstance(rec, Channel):
                channels[rec.id] = rec
                schema = schemas.get(rec.schema_id)
                kinds[rec.topic] = schema.name if schema else "?"
                continue
            if isinstance(rec, LostMessages):
                lost_clouds[rec.channel_id] += rec.count
                continue
            ch = channels[rec.channel_id]
            name = kinds[ch.topic]
            # with --pose-topic, /tf is ignored but /tf_static still gives the sensor mount
            static = ch.topic.endswith("tf_static")
            is_pose = (name in TF_SCHEMAS and (opts.pose_topic is None or static)
                       or ch.topic == opts.pose_topic)
            wants_cloud = (name in CLOUD_SCHEMAS and ch.topic not in first_cloud
                           and (opts.topic is None or ch.topic == opts.topic))
            if not (is_pose or wants_cloud):
                continue
            try:
                msg = self._decoders.decode(ch, schemas.get(ch.schema_id), rec.data)
                if wants_cloud:
                    first_cloud[ch.topic] = cloud_parts(name, msg)
                    continue
                edges = pose_edges(name, msg, default_parent=opts.map_frame, default_child=None)
            # a damaged message (bad CRC-less chunk) or a schema we cannot parse: count it
            except Exception as e:  # noqa: BLE001 - decoders raise anything on bad bytes
                undecodable[ch.topic] += 1
                log.debug("undecodable message on %s: %r", ch.topic, e)
                continue
            fox = name.startswith("foxglove.")
            samples += [(static, fox, *e) for e in edges]
        for topic, n in undecodable.items():
            self.report.losses.append(Loss(topic, "messages could not be decoded", messages=n,
                                           topics=Counter({topic: n})))
        self._kinds = kinds
        self._schemas, self._channels = schemas, channels
        self.topic = self._pick_topic(kinds, first_cloud)
        self._check_first_cloud(first_cloud.get(self.topic))
        self._build_tf(samples)
        self._check_tf()
        n = self.report.messages[self.topic] + sum(
            k for cid, k in lost_clouds.items()
            if cid in channels and channels[cid].topic == self.topic)
        last = n - 1 if opts.last is None else min(opts.last, n - 1)
        self.total = max(0, last - opts.first + 1)

    def _pick_topic(self, kinds: dict, first_cloud: dict) -> str:
        counts = Counter({t: self.report.messages[t] for t in kinds})
        clouds = {t for t, k in kinds.items() if k in CLOUD_SCHEMAS and counts[t] > 0}
        where = f"{self.path}"

        def listing(topics) -> str:
            return _describe_topics(Counter({c: counts[c] for c in topics}), kinds) or "none"

        if self.options.topic is not None:
            t = self.options.topic
            if t not in kinds:
                raise DatasetError(f"{where}: no topic {t!r}; point-cloud topics: "
                                   f"{listing(clouds)}")
            if kinds[t] not in CLOUD_SCHEMAS:
                raise DatasetError(f"{where}: topic {t!r} carries {kinds[t]}, not a point cloud "
                                   f"tisem reads ({', '.join(CLOUD_SCHEMAS)})")
            clouds = {t}
        if not clouds:
            other = [t for t, k in kinds.items() if k in UNSUPPORTED_CLOUDS]
            hint = (f"; {', '.join(f'{t} ({kinds[t]})' for t in other)} cannot be read "
                    f"(supported: {', '.join(CLOUD_SCHEMAS)})" if other else "")
            damage = ("; the file is damaged: " + "; ".join(self.report.lines())
                      if self.report.losses else "")
            raise DatasetError(f"{where}: no point-cloud messages found{hint}; topics: "
                               f"{_describe_topics(counts, kinds) or 'none'}{damage}")
        if len(clouds) > 1:
            raise DatasetError(f"{where}: several point-cloud topics, choose one with --topic: "
                               f"{listing(clouds)}")
        topic = clouds.pop()
        if topic not in first_cloud:
            raise DatasetError(f"{where}: none of the {counts[topic]} messages on {topic} "
                               f"could be decoded")
        return topic

    def _check_first_cloud(self, parts) -> None:
        """Missing fields are a property of the recording: say so before mapping anything."""
        arr, frame_id, _, _ = parts
        self.frame_id = frame_id
        opts = self.options
        needed = ["x", "y", "z", opts.prob_field or opts.label_field]
        if opts.gt_field:
            needed.append(opts.gt_field)
        missing = [f for f in needed if not pc2.has_field(arr, f)]
        if missing:
            what = {opts.label_field: "label field (--label-field)",
                    opts.prob_field: "probability field (--prob-field)",
                    opts.gt_field: "ground-truth field (--gt-field)"}
            raise DatasetError(
                f"{self.path}: the clouds on {self.topic} have no "
                f"{' and no '.join(repr(f) + ' ' + what.get(f, 'field') for f in missing)}; "
                f"their fields are: {pc2.describe_fields(arr)}")
        if not frame_id:
            raise DatasetError(f"{self.path}: the clouds on {self.topic} have an empty frame_id")

    def _build_tf(self, samples: list) -> None:
        opts = self.options
        self.tf = TfBuffer(max_extrapolation_s=opts.tf_tolerance_s)
        for static, fox, parent, child, t, xyz, q in samples:
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
                self.report.notes.append(f"foxglove transforms that never change were taken as "
                                         f"static: {', '.join(sorted(promoted))}")
        self.report.notes += [f"tf: {w}" for w in self.tf.warnings]

    def _check_tf(self) -> None:
        opts = self.options
        if opts.pose_topic is not None and opts.pose_topic not in self._kinds:
            raise DatasetError(f"{self.path}: no topic {opts.pose_topic!r}; topics: "
                               f"{_describe_topics(self.report.messages, self._kinds)}")
        if opts.pose_topic is not None and self._kinds[opts.pose_topic] not in POSE_SCHEMAS:
            raise DatasetError(f"{self.path}: --pose-topic {opts.pose_topic} carries "
                               f"{self._kinds[opts.pose_topic]}; supported: "
                               f"{', '.join(POSE_SCHEMAS)}")
        if self.frame_id.lstrip("/") == opts.map_frame.lstrip("/"):
            return
        if not self.tf.can_connect(opts.map_frame, self.frame_id):
            try:
                self.tf.lookup(opts.map_frame, self.frame_id, 0)
            except TfError as e:
                raise DatasetError(f"{self.path}: no transform from the map frame "
                                   f"{opts.map_frame!r} to the cloud frame {self.frame_id!r} "
                                   f"(--map-frame, --pose-topic): {e}") from None

    # -- pass 2
    def __len__(self) -> int:
        return self.total

    def __iter__(self) -> Iterator[Scan | SkippedScan]:
        scratch = ReadReport()               # damage was reported by the survey already
        index = -1
        targets = set()                      # channel ids of the topic (usually one)
        for rec in self._records.records(scratch):
            if isinstance(rec, Channel):
                if rec.topic == self.topic:
                    targets.add(rec.id)
                continue
            if isinstance(rec, LostMessages) and rec.channel_id in targets:
                # keep the intact file's numbering: a lost cloud is a skipped scan
                for _ in range(rec.count):
                    index += 1
                    if self._selected(index):
                        yield self._skip(SkippedScan(index, f"{self.topic}#{index}",
                                                     f"message lost in a damaged {rec.where}"))
                continue
            if not isinstance(rec, Message) or rec.channel_id not in targets:
                continue
            index += 1
            if self._selected(index):
                yield self._skip(self._scan(index, rec))

    def _selected(self, index: int) -> bool:
        return index >= self.options.first and (self.options.last is None
                                                or index <= self.options.last)

    def _skip(self, item: Scan | SkippedScan) -> Scan | SkippedScan:
        """Record a skipped scan once (the pipeline may read the log twice) and pass it on."""
        if isinstance(item, SkippedScan) and all(s.index != item.index
                                                 for s in self.report.skipped):
            self.report.skipped.append(item)
        return item

    def _scan(self, index: int, rec: Message) -> Scan | SkippedScan:
        opts = self.options
        ch = self._channels[rec.channel_id]
        name = f"{self.topic}#{index} (log time {rec.log_time / 1e9:.6f} s)"
        try:
            msg = self._decoders.decode(ch, self._schemas.get(ch.schema_id), rec.data)
            arr, frame_id, stamp_ns, T_frame_cloud = cloud_parts(self._kinds[self.topic], msg)
            sec, nsec = split_ns(stamp_ns)
            name = f"{self.topic}@{sec}.{nsec:09d}"
            T = np.eye(4) if frame_id.lstrip("/") == opts.map_frame.lstrip("/") else \
                self.tf.lookup(opts.map_frame, frame_id, stamp_ns)
            if T_frame_cloud is not None:
                T = T @ T_frame_cloud
            points = pc2.xyz(arr)
            labels = probs = gt = None
            if opts.prob_field:
                probs = self._probs(arr)
            else:
                labels, unknown = self._train_ids(arr, opts.label_field)
                self.report.unknown_labels += unknown
            if opts.gt_field:
                gt, unknown = self._train_ids(arr, opts.gt_field)
                self.report.unknown_gt_labels += unknown
            return Scan(points_sensor=points, T_world_sensor=T, stamp_s=stamp_ns / 1e9,
                        labels=labels, probs=probs, gt_labels=gt, index=index, name=name,
                        source=McapSource(topic=self.topic, frame_id=frame_id,
                                          stamp_ns=stamp_ns, log_time_ns=rec.log_time))
        except (TfError, pc2.CloudFormatError, ScanError) as e:
            return SkippedScan(index, name, str(e))
        except Exception as e:  # noqa: BLE001 - undecodable bytes raise anything
            return SkippedScan(index, name, f"cannot decode the message ({type(e).__name__}: {e})")

    def _train_ids(self, arr: np.ndarray, field_name: str) -> tuple[np.ndarray, int]:
        values = pc2.integer_labels(pc2.column(arr, field_name), field_name)
        if self.options.label_space == "raw":
            return raw_to_train(values)
        bad = (values < 0) | (values >= self.options.num_classes)
        return np.where(bad, 0, values).astype(np.int32), int(np.count_nonzero(bad))

    def _probs(self, arr: np.ndarray) -> np.ndarray:
        name = self.options.prob_field
        probs = pc2.column(arr, name)
        if probs.ndim != 2 or probs.shape[1] != self.options.num_classes:
            per = 1 if probs.ndim == 1 else probs.shape[1]
            raise pc2.CloudFormatError(f"probability field {name!r} has {per} value(s) per point; "
                                       f"the map has {self.options.num_classes} classes")
        return probs.astype(np.float32)
