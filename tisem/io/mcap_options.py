"""`McapOptions`: how `McapScanReader` turns a recording into scans.

Its own module because the options are made and checked before any file is opened (from
the command line, or from what a checkpoint stored), and both passes of the reader read them:
the survey (`tisem.io.mcap_survey`) and the scans (`tisem.io.mcap_reader`, which exports them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tisem.labels import LABEL_SPACES, NUM_CLASSES


@dataclass
class McapOptions:
    """How to turn a recording into scans (the `map_mcap.py` options)."""

    topic: str | None = None  # the cloud topic; found automatically when there is one
    label_field: str = "label"  # per-point label field ...
    label_space: str = "auto"  # ... holding raw SemanticKITTI ids, train ids, or either
    # ("auto": train ids where every value is one and some are no raw id, tisem.labels)
    prob_field: str | None = None  # or a count=C float field of class probabilities
    gt_field: str | None = None  # ground-truth label field (same label space), for metrics
    map_frame: str = "map"
    pose_topic: str | None = None  # Odometry / PoseStamped instead of /tf (dynamic)
    pose_child_frame: str | None = None  # the frame a PoseStamped is the pose of (default: the
    # top of the cloud frame's /tf_static chain)
    tf_tolerance_s: float = 0.0  # allowed extrapolation beyond a transform's samples
    # transforms the recording lacks or gets wrong (a sensor mount without /tf_static): each
    # (parent, child, x, y, z, qx, qy, qz, qw), static, in place of the recording's of `child`
    static_tf: tuple = ()
    first: int = 0  # scans by message order, last inclusive
    last: int | None = None
    num_classes: int = NUM_CLASSES

    def validate(self) -> None:
        """ValueError naming the option, its value and what is allowed."""
        if self.label_space not in LABEL_SPACES:
            raise ValueError(
                f"label_space must be one of {', '.join(LABEL_SPACES)}, got {self.label_space!r}"
            )
        tolerance = self.tf_tolerance_s
        if not (isinstance(tolerance, (int, float)) and 0 <= tolerance < math.inf):
            raise ValueError(f"tf_tolerance_s must be a finite number >= 0, got {tolerance!r}")
        for name in ("label_field", "map_frame"):
            if not (isinstance(getattr(self, name), str) and getattr(self, name)):
                raise ValueError(f"{name} must be a non-empty string, got {getattr(self, name)!r}")
        self.static_transforms()
        if not (_is_int(self.first) and self.first >= 0):
            raise ValueError(f"first must be a whole number >= 0, got {self.first!r}")
        if self.last is not None and not (_is_int(self.last) and self.last >= self.first):
            raise ValueError(
                f"last must be a whole number >= first ({self.first}) or None, got {self.last!r}"
            )
        if not (_is_int(self.num_classes) and self.num_classes >= 2):
            raise ValueError(f"num_classes must be a whole number >= 2, got {self.num_classes!r}")

    def static_transforms(self) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
        """`static_tf` as (parent, child, translation, unit quaternion xyzw); ValueError naming
        the transform where one is not a transform. A quaternion is normalised as tf2 does,
        but only where its norm is within 1 % of 1: anything else is a typing error (Euler
        angles, a missing component), not a rotation."""
        out, children = [], set()
        for item in self.static_tf:
            where = f"static_tf {list(item)!r}" if isinstance(item, (list, tuple)) else ""
            if not (isinstance(item, (list, tuple)) and len(item) == 9):
                raise ValueError(
                    f"static_tf: each transform is (parent, child, x, y, z, qx, qy, qz, qw), "
                    f"got {item!r}"
                )
            parent, child, *numbers = item
            if not (isinstance(parent, str) and isinstance(child, str)):
                raise ValueError(f"{where}: the parent and child frames must be names")
            parent, child = parent.lstrip("/"), child.lstrip("/")
            if not parent or not child or parent == child:
                raise ValueError(f"{where}: needs two different, non-empty frame names")
            if child in children:
                raise ValueError(f"{where}: frame {child!r} is given a transform twice")
            children.add(child)
            if not all(
                isinstance(v, (int, float, np.number)) and not isinstance(v, bool) for v in numbers
            ):
                raise ValueError(f"{where}: x y z qx qy qz qw must be numbers")
            values = np.array(numbers, np.float64)
            if not np.all(np.isfinite(values)):
                raise ValueError(f"{where}: x y z qx qy qz qw must be finite")
            norm = float(np.linalg.norm(values[3:]))
            if abs(norm - 1.0) > 0.01:
                raise ValueError(
                    f"{where}: the quaternion qx qy qz qw has norm {norm:.4g}, not 1 "
                    f"(a rotation by quaternion, not Euler angles; no rotation is 0 0 0 1)"
                )
            out.append((parent, child, values[:3], values[3:] / norm))
        return out


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)
