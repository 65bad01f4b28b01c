"""The one judgement of every fuzz case: what a reader made of a damaged input.

Outcomes:
- identical: every scan read equals the intact input's scan of that index byte for byte
  (points, labels, ground truth, probabilities, pose, stamp, index), none is missing;
- reported: some scans were skipped with a reason, marked suspect in the read report, or lost
  with a loss in the report, or their labels were counted as unknown; every other scan is
  identical;
- refused: the reader refused the whole input with the project's error (`DatasetError`, or
  `ScanError`);
- undetectable: a mutation that leaves a valid input (another value in a valid place) changed
  a scan without a report, which no reader can avoid;
- failure: any other exception, or damage that nothing reports: a scan that differs, an index
  read twice, scans that vanish from an MCAP file without a loss in its report.
"""

from __future__ import annotations

import json
import traceback
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tisem.errors import DatasetError, ScanError, SkippedScan
from tisem.scan import Scan

OUTCOMES = ("identical", "reported", "refused", "undetectable", "failure")


@dataclass
class Outcome:
    kind: str  # one of OUTCOMES
    detail: str = ""


def _bytes(a: np.ndarray | None) -> bytes | None:
    return None if a is None else np.ascontiguousarray(a).tobytes()


def signature(scan: Scan) -> tuple:
    """What must be byte-identical between a scan and the intact input's scan."""
    return (
        scan.index,
        _bytes(scan.points_sensor),
        _bytes(scan.labels),
        _bytes(scan.probs),
        _bytes(scan.gt_labels),
        _bytes(scan.T_world_sensor),
        float(scan.stamp_s),
    )


def reference(items) -> dict[int, Scan]:
    """The scans of an intact input, by index (the input must read without a skipped scan)."""
    scans = list(items)
    bad = [s for s in scans if not isinstance(s, Scan)]
    if bad:
        raise ValueError(f"the intact input has skipped scans: {bad}")
    return {s.index: s for s in scans}


def _unknown(scan: Scan) -> tuple[int, int]:
    src = scan.source
    return (src.unknown_raw_ids, src.unknown_gt_ids) if src is not None else (0, 0)


def _labels_reported(scan: Scan, ref: Scan) -> bool:
    """Only labels changed, each to 0, and at least as many were counted unknown."""
    if (
        _bytes(scan.points_sensor),
        _bytes(scan.T_world_sensor),
        scan.stamp_s,
        _bytes(scan.probs),
    ) != (_bytes(ref.points_sensor), _bytes(ref.T_world_sensor), ref.stamp_s, _bytes(ref.probs)):
        return False
    (unknown, unknown_gt), (was, was_gt) = _unknown(scan), _unknown(ref)
    for new, old, more in (
        (scan.labels, ref.labels, unknown - was),
        (scan.gt_labels, ref.gt_labels, unknown_gt - was_gt),
    ):
        if new is None or old is None:
            if (new is None) != (old is None):
                return False
            continue
        changed = new != old
        if np.any(new[changed] != 0) or np.count_nonzero(changed) > more:
            return False
    return True


def judge(
    items: list,
    ref: dict[int, Scan],
    detectable: bool,
    suspect=(),
    losses: bool = False,
    vanish_needs_loss: bool = False,
) -> Outcome:
    """The outcome of the items (`Scan | SkippedScan`) one read of a damaged input gave."""
    counts = Counter(item.index for item in items)
    twice = sorted(k for k, n in counts.items() if n > 1 and k not in suspect)
    if twice:
        return Outcome("failure", f"scan(s) {twice} read more than once")
    silent, unseen, reported = [], [], False
    for item in items:
        if isinstance(item, SkippedScan):
            reported = True
            continue
        old = ref.get(item.index)
        if old is not None and signature(item) == signature(old):
            continue
        if item.index in suspect or (old is not None and _labels_reported(item, old)):
            reported = True
        elif detectable:
            silent.append(item.index)
        else:
            unseen.append(item.index)
    if silent:
        return Outcome(
            "failure", f"scan(s) {silent} differ from the intact input and nothing reports it"
        )
    missing = sorted(set(ref) - set(counts))
    if missing and vanish_needs_loss and not losses and detectable:
        return Outcome("failure", f"scan(s) {missing} vanished without a loss in the report")
    if unseen:
        return Outcome("undetectable", f"scan(s) {unseen} changed")
    if reported or missing:
        return Outcome(
            "reported",
            f"{sum(isinstance(i, SkippedScan) for i in items)} skipped, {len(missing)} missing",
        )
    return Outcome("identical")


def _failure(e: BaseException) -> Outcome:
    frame = traceback.extract_tb(e.__traceback__)[-1]
    where = f"{Path(frame.filename).name}:{frame.lineno}"
    return Outcome("failure", f"{type(e).__name__} at {where}: {str(e)[:300]}")


def judge_bag(path: Path, ref: dict[int, Scan], detectable: bool) -> Outcome:
    """Read a damaged recording twice (as a run does, for the final map) and judge it: any
    recording `open_scan_reader` takes (an MCAP file, a ROS 1 bag, ...)."""
    from tisem.io.bag_open import open_scan_reader

    return judge_recording(open_scan_reader, path, ref, detectable)


def judge_recording(open_reader, path: Path, ref: dict[int, Scan], detectable: bool) -> Outcome:
    try:
        reader = open_reader(path)
        first, second = list(reader), list(reader)
        json.dumps(reader.report.to_dict())
        reader.report.lines()
    except (DatasetError, ScanError) as e:
        return Outcome("refused", str(e)[:300])
    except Exception as e:  # noqa: BLE001 - the point: anything else is a failure
        return _failure(e)
    if [_item_key(i) for i in first] != [_item_key(i) for i in second]:
        return Outcome("failure", "a second read of the file gave other scans")
    report = reader.report
    return judge(
        first,
        ref,
        detectable,
        suspect=report.suspect,
        losses=bool(report.losses),
        vanish_needs_loss=True,
    )


def judge_kitti(folder: Path, ref: dict[int, Scan], detectable: bool) -> Outcome:
    from tisem.io.semantickitti import SemanticKittiSequence

    try:
        items = list(SemanticKittiSequence(folder))
    except (DatasetError, ScanError) as e:
        return Outcome("refused", str(e)[:300])
    except Exception as e:  # noqa: BLE001 - the point: anything else is a failure
        return _failure(e)
    return judge(items, ref, detectable)


def _item_key(item) -> tuple:
    return signature(item) if isinstance(item, Scan) else ("skipped", item.index, item.reason)
