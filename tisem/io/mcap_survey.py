"""The first pass of `McapScanReader` over a recording: the pose messages, the message counts,
the cloud topic, and whether its clouds have what the options need.

Apart from the reader (`tisem.io.mcap_reader`) because this pass runs once, before any
mapping, and leaves only its findings behind: every "this cannot work" error of a recording
comes from here (with the damage that may be why), and the scans are then read without it.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter

from mcap.records import Channel, Schema

from tisem.errors import DatasetError
from tisem.io import pointcloud2 as pc2
from tisem.io.mcap_items import Unvouched
from tisem.io.mcap_messages import (
    CLOUD_SCHEMAS,
    POSE_SCHEMAS,
    TF_SCHEMAS,
    UNSUPPORTED_CLOUDS,
    MessageDecoders,
    cloud_parts,
    pose_edges,
)
from tisem.io.mcap_options import McapOptions
from tisem.io.mcap_records import Loss, LostMessages, McapRecords, ReadReport
from tisem.io.mcap_report import error_text, unnamed_channel_id
from tisem.io.tf import TfBuffer, TfError
from tisem.labels import SPACE_SEARCH_LIMIT, deciding_space

log = logging.getLogger(__name__)

# what segmentation nodes call a per-point class field, named in the refusal of a recording
# whose clouds lack the --label-field asked for (a guess would map the wrong field silently)
_LABEL_NAMES = ("label", "labels", "class", "class_id", "semantic", "semantic_label", "sem_label")


def _may_hold_poses(lost_topics, pose_topics: set[str], channels: dict) -> bool:
    """Whether a loss may have held pose messages. One counted before its channel's Channel
    record was read names the channel by id (a file without a summary, read linearly, whose
    damaged chunk held a channel's first messages): it held poses if that channel turned out
    to be a pose topic's, and may have if its record was never read."""
    for name in lost_topics:
        cid = unnamed_channel_id(name)
        if name in pose_topics or (
            cid is not None and (cid not in channels or channels[cid].topic in pose_topics)
        ):
            return True
    return False


def _describe_topics(counts: Counter, kinds: dict) -> str:
    return ", ".join(f"{t} ({kinds.get(t, '?')}, {n} msgs)" for t, n in sorted(counts.items()))


class Survey:
    """What the first pass found: `schemas`, `channels` (by id), `kinds` (topic -> schema
    name), the cloud `topic` and its `frame_id`, the transform buffer `tf`, `total` (scans
    the options select), `poses_lost` (pose messages were lost or undecodable) and
    `unvouched_mount` (why every scan is suspect when the sensor's mount came from a chunk
    that failed its checks, `_mount_from_damage`; None otherwise).

    Raises `DatasetError` when nothing can be mapped: no cloud topic, an ambiguous one, a
    missing field, no transform path. Damage found is appended to `report`.
    """

    def __init__(
        self,
        path: str,
        options: McapOptions,
        records: McapRecords,
        decoders: MessageDecoders,
        report: ReadReport,
    ) -> None:
        self.path, self.options, self.report = path, options, report
        # (--label-space auto) per (cloud topic, label field): the space of the topic's first
        # cloud whose field fits only one, which its clouds that fit both are read in
        self.label_spaces: dict[tuple[str, str], str] = {}
        fields = [] if options.prob_field else [options.label_field]
        fields += [options.gt_field] if options.gt_field else []
        self._label_fields = fields if options.label_space == "auto" else []
        self._searched: Counter = Counter()  # topic -> clouds looked at for it
        self._survey(records, decoders)

    def _survey(self, records: McapRecords, decoders: MessageDecoders) -> None:
        opts, report = self.options, self.report
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
        unvouched: list[Unvouched] = []
        self.unvouched_mount: str | None = None
        for rec in records.records(report):
            if isinstance(rec, Unvouched):
                unvouched.append(rec)
                continue
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
                # counted on a channel only where its record came first, as the scans' pass
                # (McapScanReader) numbers them: a loss on an id named later is unknown there
                if rec.channel_id in channels:
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
            on_topic = name in CLOUD_SCHEMAS and (opts.topic is None or ch.topic == opts.topic)
            wants_cloud = on_topic and ch.topic not in first_cloud
            # after a topic's first usable cloud, its clouds are decoded only while the space of
            # a label field is open (in a recording of labels, the first cloud nearly always
            # decides it: road, terrain and fence are ids raw SemanticKITTI does not use)
            wants_space = on_topic and not wants_cloud and self._space_open(ch.topic)
            if not (is_pose or wants_cloud or wants_space):
                continue
            try:
                msg = decoders.decode(ch, schemas.get(ch.schema_id), rec.data)
                if wants_cloud or wants_space:
                    parts = cloud_parts(name, msg)
                    usable = self._cloud_problem(parts, ch.topic) is None
                    if wants_cloud and usable:
                        first_cloud[ch.topic] = parts
                    elif wants_cloud:  # one odd cloud must not refuse the file
                        misfits.setdefault(ch.topic, parts)
                    if usable:  # (a cloud the scans skip is no evidence)
                        self._note_label_spaces(ch.topic, parts[0])
                    continue
                edges = pose_edges(name, msg, default_parent=opts.map_frame, default_child=None)
            # a damaged message (in a chunk without CRC) or a schema we cannot parse; a bad
            # cloud is skipped with its reason when the scans are read, so only its reason is
            # kept here
            except Exception as e:  # noqa: BLE001 - decoders raise anything on bad bytes
                why = error_text(e)
                if wants_cloud:
                    self._cloud_errors.setdefault(ch.topic, why)
                elif not wants_space:  # (such a cloud's scan is skipped, saying why, when read)
                    undecodable[ch.topic] += 1
                    pose_errors.setdefault(ch.topic, why)
                continue
            fox = name.startswith("foxglove.")
            samples += [(static, fox, *e) for e in edges]
        for topic, n in undecodable.items():
            report.losses.append(
                Loss(
                    topic,
                    f"messages could not be decoded (the first: {pose_errors[topic][:200]})",
                    messages=n,
                    topics=Counter({topic: n}),
                )
            )
        pose_topics = {t for t, k in kinds.items() if k in TF_SCHEMAS or t == opts.pose_topic}
        # a lost pose message changes the poses interpolated across where it was
        self.poses_lost = bool(undecodable) or any(
            loss.uncounted or _may_hold_poses(loss.topics, pose_topics, channels)
            for loss in report.losses
        )
        self.kinds = kinds
        self.schemas, self.channels = schemas, channels
        try:
            self.topic = self._pick_topic(kinds, {*first_cloud, *misfits}, set(first_cloud))
            if self.topic not in first_cloud:  # no cloud has what the options need
                raise DatasetError(self._cloud_problem(misfits[self.topic], self.topic))
            self.frame_id = first_cloud[self.topic][1]
            self._build_tf(samples)
            try:
                self._check_tf()
            except DatasetError:
                if not self._mount_from_damage(samples, unvouched, schemas, decoders):
                    raise
        except DatasetError as e:  # what was lost may be why
            raise DatasetError(f"{e}{self._damage()}") from None
        n = report.messages[self.topic] + sum(
            k
            for cid, k in lost_clouds.items()
            if cid in channels and channels[cid].topic == self.topic
        )
        last = n - 1 if opts.last is None else min(opts.last, n - 1)
        self.total = max(0, last - opts.first + 1)

    def _space_open(self, topic: str) -> bool:
        """Whether a label field of `topic` still waits for a cloud that decides its space
        (within the first SPACE_SEARCH_LIMIT clouds: a field of zeros never decides)."""
        return self._searched[topic] < SPACE_SEARCH_LIMIT and any(
            (topic, f) not in self.label_spaces for f in self._label_fields
        )

    def _note_label_spaces(self, topic: str, arr) -> None:
        """The space of each label field of `topic` not decided yet, where this usable cloud's
        values fit only one (`tisem.labels.deciding_space`)."""
        self._searched[topic] += 1
        for field in self._label_fields:
            if (topic, field) in self.label_spaces:
                continue
            try:
                values = pc2.integer_labels(pc2.column(arr, field), field)[0]
            except Exception:  # noqa: BLE001 - a field of another type: its scans say so
                continue
            space = deciding_space(values)
            if space is not None:
                self.label_spaces[(topic, field)] = space

    def _pick_topic(self, kinds: dict, decoded: set, usable: set) -> str:
        """The cloud topic: the one asked for, the only one, or the only one whose clouds
        carry the fields the options need (`usable`: a raw sensor topic beside the labelled
        one a segmentation node publishes); DatasetError otherwise."""
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
        if len(clouds) > 1 and len(clouds & usable) == 1:
            (topic,) = clouds & usable
            log.info(
                "%s: several point-cloud topics; mapping %s, the one whose clouds carry the "
                "fields asked for (--topic to choose): %s",
                where,
                topic,
                listing(clouds),
            )
            return topic
        if len(clouds) > 1:
            carry = f"; {listing(clouds & usable)} carry the fields asked for" if usable else ""
            raise DatasetError(
                f"{where}: several point-cloud topics, choose one with --topic: "
                f"{listing(clouds)}{carry}"
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
            hint = ""
            if opts.label_field in missing and not opts.prob_field:
                named = [f for f in _LABEL_NAMES if pc2.has_field(arr, f)]
                hint = f" (the labels? --label-field {named[0]})" if named else ""
            return (
                f"{self.path}: the clouds on {topic} have no "
                f"{' and no '.join(repr(f) + ' ' + what.get(f, 'field') for f in missing)}; "
                f"their fields are: {pc2.describe_fields(arr)}{hint}"
            )
        if not frame_id:
            return f"{self.path}: the clouds on {topic} have an empty frame_id"
        return None

    def _build_tf(self, samples: list) -> None:
        opts = self.options
        self.tf = TfBuffer(max_extrapolation_s=opts.tf_tolerance_s)
        # the user's transforms (--static-tf) first, in place of the recording's of their child
        given = {}
        for parent, child, xyz, q in opts.static_transforms():
            self.tf.add(parent, child, 0, xyz, q, static=True)
            given[child] = parent
        replaced = Counter()

        def replaces(child: str) -> bool:
            if child.lstrip("/") in given:
                replaced[child.lstrip("/")] += 1
                return True
            return False

        for static, _fox, parent, child, t, xyz, q in samples:
            if static and not replaces(child):
                self.tf.add(parent, child, t, xyz, q, static=True)
        # a PoseStamped names no child: by default it is the pose of the top of the sensor's
        # static mount (base_link for base_link -> velodyne), or of the sensor when unmounted
        child_default = opts.pose_child_frame or self.tf.root_of(self.frame_id)
        fox_children = set()
        for static, fox, parent, child, t, xyz, q in samples:
            if static or replaces(child or child_default):
                continue
            self.tf.add(parent, child or child_default, t, xyz, q)
            if fox:
                fox_children.add((child or child_default).lstrip("/"))
        notes = []
        if fox_children:
            promoted = self.tf.promote_constant_edges(fox_children)
            if promoted:
                notes.append(
                    f"foxglove transforms that never change were taken as "
                    f"static: {', '.join(sorted(promoted))}"
                )
        notes += [
            f"tf: {given[child]} -> {child} from --static-tf, in place of the recording's "
            f"{n} transform(s) of {child}"
            for child, n in replaced.items()
        ]
        notes += [f"tf: {w}" for w in self.tf.warnings]
        # (built again with a mount read from damage, `_mount_from_damage`: its notes once)
        for note in getattr(self, "_tf_notes", []):
            self.report.notes.remove(note)
        self._tf_notes = notes
        self.report.notes += notes

    def _mount_from_damage(
        self, samples: list, unvouched: list[Unvouched], schemas: dict, decoders
    ) -> bool:
        """Where the map frame does not reach the cloud's, the /tf_static messages read from
        the start of chunks that failed their checks (`Unvouched`), for frames no intact
        message gives: whether the transforms then connect (`unvouched_mount` says why every
        scan is suspect). A recording holds its sensor's mount once, in its first chunk, so
        one damaged byte there would otherwise refuse every scan of an intact rest."""
        given = {child.lstrip("/") for static, _f, _p, child, *_ in samples if static}
        extra, used = [], {}
        for n, u in enumerate(unvouched):
            schema = u.schema or schemas.get(u.channel.schema_id)
            if schema is None or schema.name not in TF_SCHEMAS:
                continue
            # on ids no channel and no schema has: decoders keep one decoder per channel id and
            # the decoder factories one per schema id, and the salvaged records' ids are their
            # file's own (a split file numbers its own)
            channel = dataclasses.replace(u.channel, id=-1 - n)
            try:
                msg = decoders.decode(
                    channel, dataclasses.replace(schema, id=-1 - n), u.message.data
                )
                edges = pose_edges(
                    schema.name, msg, default_parent=self.options.map_frame, default_child=None
                )
            except Exception:  # noqa: BLE001 - decoders raise anything on bad bytes
                continue
            for parent, child, t, xyz, q in edges:
                if child.lstrip("/") not in given:
                    extra.append((True, False, parent, child, t, xyz, q))
                    used.setdefault(f"{parent.lstrip('/')} -> {child.lstrip('/')}", u.where)
        if not extra:
            return False
        self._build_tf(samples + extra)
        try:
            self._check_tf()
        except DatasetError:
            self._build_tf(samples)
            return False
        self.unvouched_mount = (
            "its pose uses a static transform read from a damaged chunk, whose bytes nothing "
            "vouches for ("
            + "; ".join(f"{edge} from the {where}" for edge, where in used.items())
            + "); --static-tf gives it instead"
        )
        return True

    def _check_tf(self) -> None:
        opts = self.options
        if opts.pose_topic is not None and opts.pose_topic not in self.kinds:
            raise DatasetError(
                f"{self.path}: no topic {opts.pose_topic!r}; topics: "
                f"{_describe_topics(self.report.messages, self.kinds)}"
            )
        if opts.pose_topic is not None and self.kinds[opts.pose_topic] not in POSE_SCHEMAS:
            raise DatasetError(
                f"{self.path}: --pose-topic {opts.pose_topic} carries "
                f"{self.kinds[opts.pose_topic]}; supported: "
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
                    f"(--map-frame, --pose-topic; a sensor mount the recording lacks: "
                    f"--static-tf X Y Z QX QY QZ QW PARENT CHILD): {e}"
                ) from None
