"""A numpy transform buffer: the /tf + /tf_static tree, looked up at any stamp.

Semantics follow tf2 so that users get the poses they would get in ROS:
- the tree maps each child frame to one parent; an edge is static (/tf_static: valid at all
  times, the latest message wins) or dynamic (a time series);
- a lookup walks both frames up to their common ancestor and composes the edges;
- a dynamic edge is interpolated between the samples around the stamp (linear in translation,
  slerp in rotation); a stamp outside an edge's samples is an `ExtrapolationError` (unless
  within `max_extrapolation_s`, then the nearest sample is used), a missing link a
  `ConnectivityError`. Both name the frames and the times involved.
Stamps are integer nanoseconds (ROS `sec`/`nanosec`), so equal stamps compare exactly.

What pose messages (TFMessage, Odometry, PoseStamped, foxglove.FrameTransform(s)) carry is
turned into edges by `tisem.io.mcap_messages.pose_edges`.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
GAP_FACTOR = 1.5  # samples this many median spacings apart leave a gap between them


class TfError(LookupError):
    """A transform cannot be looked up (the message says which and why)."""


class ConnectivityError(TfError):
    """The two frames are not connected in the tree."""


class ExtrapolationError(TfError):
    """The stamp lies outside the time range of an edge of the chain."""


# ---- rotations -------------------------------------------------------------------------------


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions x, y, z, w (normalised here) -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """A 3x3 matrix -> unit quaternion x, y, z, w (w >= 0).

    Matrices from text files (KITTI poses) are orthonormal only to ~1e-6; the quaternion of the
    nearest rotation (SVD) is the best a tf message can carry.
    """
    R = np.asarray(R, dtype=np.float64)
    U, _, Vt = np.linalg.svd(R)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    # Shepperd: pick the largest of w, x, y, z to divide by, for accuracy near 180 degrees
    t = np.trace(R)
    diag = np.diag(R)
    i = int(np.argmax([t, *diag]))
    if i == 0:
        s = 2.0 * np.sqrt(1.0 + t)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    elif i == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif i == 2:
        s = 2.0 * np.sqrt(1.0 - R[0, 0] + R[1, 1] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 - R[0, 0] - R[1, 1] + R[2, 2])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def slerp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Spherical interpolation (K, 4) x (K, 4) x (K,) -> (K, 4), along the shorter arc."""
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    sin = np.sin(theta)
    near = sin < 1e-12  # (almost) equal rotations: lerp is exact enough
    safe = np.where(near, 1.0, sin)
    a = np.where(near, 1.0 - w, np.sin((1.0 - w) * theta) / safe)
    b = np.where(near, w, np.sin(w * theta) / safe)
    q = a[:, None] * q0 + b[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def make_transform(translation: ArrayLike, rotation_xyzw: ArrayLike) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(rotation_xyzw)
    T[:3, 3] = translation
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4)."""
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = R
    out[..., :3, 3] = -(R @ T[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def _frame(name: str) -> str:
    return name.lstrip("/")  # ROS 1 frames may carry a leading '/'


# ---- the buffer ------------------------------------------------------------------------------


@dataclass
class _Edge:
    parent: str
    static: bool
    samples: list = field(default_factory=list)  # (stamp_ns, xyz, quat) as added
    stamps: np.ndarray | None = None  # sorted, unique; built lazily
    trans: np.ndarray | None = None
    quats: np.ndarray | None = None

    def finalize(self) -> None:
        if self.stamps is not None and len(self.stamps) == len(self.samples):
            return
        stamps = np.array([s[0] for s in self.samples], dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        # a repeated stamp keeps its latest sample (like tf2 overwriting)
        keep = np.ones(len(order), bool)
        keep[:-1] = stamps[order][1:] != stamps[order][:-1]
        order = order[keep]
        self.samples = [self.samples[i] for i in order]
        self.stamps = stamps[order]
        self.trans = np.array([s[1] for s in self.samples], dtype=np.float64).reshape(-1, 3)
        self.quats = np.array([s[2] for s in self.samples], dtype=np.float64).reshape(-1, 4)

    def at(self, child: str, stamps_ns: np.ndarray, max_extrapolation_ns: int) -> np.ndarray:
        """(K, 4, 4) T_parent_child at the given stamps."""
        self.finalize()
        if self.static:
            T = make_transform(self.trans[-1], self.quats[-1])
            return np.broadcast_to(T, (len(stamps_ns), 4, 4))
        lo, hi = self.stamps[0], self.stamps[-1]
        bad = (stamps_ns < lo - max_extrapolation_ns) | (stamps_ns > hi + max_extrapolation_ns)
        if np.any(bad):
            t = int(stamps_ns[np.argmax(bad)])
            side = (
                f"{(lo - t) / 1e6:.3f} ms before its first"
                if t < lo
                else f"{(t - hi) / 1e6:.3f} ms after its last"
            )
            raise ExtrapolationError(
                f"edge {self.parent} -> {child} has {len(self.stamps)} sample(s) from "
                f"{lo / 1e9:.6f} s to {hi / 1e9:.6f} s; the stamp {t / 1e9:.6f} s is {side} sample"
            )
        t = np.clip(stamps_ns, lo, hi)
        if len(self.stamps) == 1:
            return np.broadcast_to(make_transform(self.trans[0], self.quats[0]), (len(t), 4, 4))
        i1 = np.clip(np.searchsorted(self.stamps, t, side="right"), 1, len(self.stamps) - 1)
        i0 = i1 - 1
        s0, s1 = self.stamps[i0], self.stamps[i1]
        w = (t - s0).astype(np.float64) / (s1 - s0).astype(np.float64)
        T = np.zeros((len(t), 4, 4))
        T[:, :3, :3] = quat_to_matrix(slerp(self.quats[i0], self.quats[i1], w))
        T[:, :3, 3] = self.trans[i0] + w[:, None] * (self.trans[i1] - self.trans[i0])
        T[:, 3, 3] = 1.0
        # a stamp that is a sample's own gets that sample bit for bit, as an edge of that one
        # sample gives it (slerp at w = 0 or 1 rounds otherwise): a scan's pose must not
        # depend on whether the samples beside it were read (a cut file, a lost chunk)
        for own, i in ((t == s0, i0), (t == s1, i1)):
            if np.any(own):
                T[own, :3, :3] = quat_to_matrix(self.quats[i[own]])
                T[own, :3, 3] = self.trans[i[own]]
        return T


class TfBuffer:
    """All transforms of a log, looked up at any stamp. See the module docstring."""

    def __init__(self, max_extrapolation_s: float = 0.0) -> None:
        self.max_extrapolation_ns = int(round(max_extrapolation_s * 1e9))
        self._edges: dict[str, _Edge] = {}  # child -> edge to its parent
        self._ignored: Counter = Counter()  # why transforms were ignored -> how many

    # -- filling
    def add(
        self,
        parent: str,
        child: str,
        stamp_ns: int,
        translation: ArrayLike,
        rotation_xyzw: ArrayLike,
        static: bool = False,
    ) -> None:
        parent, child = _frame(parent), _frame(child)
        if not parent or not child or parent == child:
            self._ignore(f"with frames {parent!r} -> {child!r}")
            return
        q = np.asarray(rotation_xyzw, dtype=np.float64)
        xyz = np.asarray(translation, dtype=np.float64)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(xyz))):
            self._ignore(f"{parent} -> {child} with non-finite values")
            return
        if q.shape != (4,) or xyz.shape != (3,) or np.abs(q).max() < 1e-9:
            self._ignore(f"{parent} -> {child} with a zero quaternion")
            return
        q = q / np.abs(q).max()  # (the norm of huge components would overflow)
        if not _INT64_MIN <= int(stamp_ns) <= _INT64_MAX:
            self._ignore(f"{parent} -> {child} stamped outside 64-bit nanoseconds")
            return
        edge = self._edges.get(child)
        if edge is None:
            edge = self._edges[child] = _Edge(parent, static)
        elif edge.parent != parent or edge.static != static:
            # tf2 would re-parent; a log that does so is ambiguous, so keep the first and say so
            self._ignore(
                f"giving frame {child!r} the parent {parent!r} "
                f"({'static' if static else 'dynamic'}); its parent is "
                f"{edge.parent!r} ({'static' if edge.static else 'dynamic'})"
            )
            return
        if static:
            edge.samples = [(int(stamp_ns), xyz, q)]  # /tf_static: the latest wins
            edge.stamps = None
        else:
            edge.samples.append((int(stamp_ns), xyz, q))

    def _ignore(self, what: str) -> None:
        self._ignored[what] += 1

    @property
    def warnings(self) -> list[str]:
        """One line per kind of ignored transform, with how many there were."""
        return [f"ignored {n} transform(s) {what}" for what, n in self._ignored.items()]

    def _ignored_line(self) -> str:
        return f"; {'; '.join(self.warnings)}" if self._ignored else ""

    def promote_constant_edges(self, children: Collection[str] | None = None) -> list[str]:
        """Make dynamic edges whose samples never change static (returns their children);
        `children` limits this to those edges.

        Foxglove FrameTransforms have no static flag: a sensor mount logged once would otherwise
        be usable only at that one stamp.
        """
        promoted = []
        for child, edge in self._edges.items():
            if edge.static or (children is not None and child not in children):
                continue
            edge.finalize()
            if np.all(edge.trans == edge.trans[0]) and np.all(edge.quats == edge.quats[0]):
                edge.static = True
                promoted.append(child)
        return promoted

    # -- queries
    @property
    def frames(self) -> set[str]:
        return set(self._edges) | {e.parent for e in self._edges.values()}

    def _ancestors(self, frame: str) -> list[str]:
        chain, seen = [frame], {frame}
        while chain[-1] in self._edges:
            parent = self._edges[chain[-1]].parent
            if parent in seen:
                raise ConnectivityError(f"the tf tree has a cycle through {parent!r}")
            chain.append(parent)
            seen.add(parent)
        return chain

    def root_of(self, frame: str) -> str:
        """The top of `frame`'s chain (the frame itself when it has no parent)."""
        return self._ancestors(_frame(frame))[-1]

    def can_connect(self, target: str, source: str) -> bool:
        try:
            self._path(_frame(target), _frame(source))
            return True
        except ConnectivityError:
            return False

    def _path(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """Frames from source up to (excluding) the common ancestor, and the same for target."""
        known = self.frames
        for name in (target, source):
            if name not in known:
                raise ConnectivityError(
                    f"frame {name!r} does not appear in any transform; "
                    f"known frames: {', '.join(sorted(known)) or 'none'}"
                    f"{self._ignored_line()}"
                )
        up_s, up_t = self._ancestors(source), self._ancestors(target)
        common = next((f for f in up_s if f in set(up_t)), None)
        if common is None:
            raise ConnectivityError(
                f"frames {target!r} and {source!r} are not connected: {source!r} leads up to "
                f"{up_s[-1]!r}, {target!r} up to {up_t[-1]!r}; tree: {self.describe()}"
                f"{self._ignored_line()}"
            )
        return up_s[: up_s.index(common)], up_t[: up_t.index(common)]

    def lookup_many(self, target: str, source: str, stamps_ns: ArrayLike) -> np.ndarray:
        """(K, 4, 4) T_target_source at each stamp (a point in `source` -> `target`)."""
        target, source = _frame(target), _frame(source)
        stamps = np.atleast_1d(np.asarray(stamps_ns, dtype=np.int64))
        from_source, from_target = self._path(target, source)

        def to_common(children: list[str]) -> np.ndarray:
            T = np.broadcast_to(np.eye(4), (len(stamps), 4, 4))
            for child in children:  # child -> ... -> common, innermost first
                try:
                    T = self._edges[child].at(child, stamps, self.max_extrapolation_ns) @ T
                except ExtrapolationError as e:
                    raise ExtrapolationError(f"cannot look up {target} -> {source}: {e}") from None
            return T

        return invert(to_common(from_target)) @ to_common(from_source)

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        """(4, 4) T_target_source at one stamp."""
        return self.lookup_many(target, source, [stamp_ns])[0]

    def interpolation_gap(
        self, target: str, source: str, stamp_ns: int, factor: float = GAP_FACTOR
    ) -> str | None:
        """Where a lookup at `stamp_ns` interpolates over a gap in a dynamic edge's samples
        (two samples more than `factor` times the edge's median spacing apart, or the stamp
        outside the samples): what a lost /tf message looks like from here. None otherwise,
        and for a stamp that is a sample's own (the pose is that sample, whatever was lost
        beside it: a recording whose /tf is stamped with its clouds' stamps)."""
        target, source = _frame(target), _frame(source)
        from_source, from_target = self._path(target, source)
        for child in from_source + from_target:
            edge = self._edges[child]
            edge.finalize()
            if edge.static:
                continue
            stamps = edge.stamps
            i = int(np.searchsorted(stamps, stamp_ns, side="right"))
            if i > 0 and stamps[i - 1] == stamp_ns:
                continue
            if len(stamps) < 3:  # (no spacing to tell a gap by: the rest may all be lost)
                at = " and ".join(f"{t / 1e9:.6f} s" for t in stamps)
                return (
                    f"edge {edge.parent} -> {child} has {len(stamps)} sample(s) left, at {at}: "
                    f"how far apart its samples were is unknown"
                )
            spacing = float(np.median(np.diff(stamps)))
            name, spaced = (
                f"edge {edge.parent} -> {child}",
                f"its median spacing is {spacing / 1e6:.1f} ms",
            )
            if i == 0:
                return f"{name} has no samples before {stamps[0] / 1e9:.6f} s, its first ({spaced})"
            if i == len(stamps):
                return f"{name} has no samples after {stamps[-1] / 1e9:.6f} s, its last ({spaced})"
            if stamps[i] - stamps[i - 1] > factor * spacing:
                return (
                    f"{name} has no samples from {stamps[i - 1] / 1e9:.6f} s to "
                    f"{stamps[i] / 1e9:.6f} s around the stamp ({spaced})"
                )
        return None

    def describe(self) -> str:
        parts = []
        for child, e in sorted(self._edges.items(), key=lambda kv: (kv[1].parent, kv[0])):
            e.finalize()
            kind = (
                "static"
                if e.static
                else f"{len(e.stamps)} samples {e.stamps[0] / 1e9:.3f}-{e.stamps[-1] / 1e9:.3f} s"
            )
            parts.append(f"{e.parent} -> {child} ({kind})")
        return "; ".join(parts) or "empty"
