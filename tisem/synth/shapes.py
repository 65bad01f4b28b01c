"""The primitives the synthetic world is made of: boxes, vertical cylinders and ellipsoids.

Each kind is a struct-of-arrays (one row per primitive, its raw SemanticKITTI label and its
instance id), so the LiDAR intersects thousands of them with a few numpy calls. A
`ShapeBuilder` collects primitives in route coordinates and places them in the world.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, fields

import numpy as np

from tisem.synth.route import Route

# a primitive's bounding vertical cylinder: centre xy (n, 2), radius (n,), z min (n,), z max (n,)
Footprint = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@dataclass
class _Shapes:
    """Struct-of-arrays of one primitive kind; `label` is the raw id, `instance` 0 for stuff."""

    label: np.ndarray  # (n,) uint32
    instance: np.ndarray  # (n,) uint32

    def __len__(self) -> int:
        return len(self.label)

    @classmethod
    def concat(cls, parts):
        return cls(
            **{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)}
        )

    def footprint(self) -> Footprint:
        """The bounding vertical cylinders: the LiDAR culls against them by azimuth and
        elevation before any exact intersection."""
        raise NotImplementedError


@dataclass
class Boxes(_Shapes):
    center: np.ndarray  # (n, 3)
    half: np.ndarray  # (n, 3) half extents along the box's own x (yaw direction), y, z
    yaw: np.ndarray  # (n,) radians about world z

    def footprint(self) -> Footprint:
        return (
            self.center[:, :2],
            np.hypot(self.half[:, 0], self.half[:, 1]),
            self.center[:, 2] - self.half[:, 2],
            self.center[:, 2] + self.half[:, 2],
        )


@dataclass
class Cylinders(_Shapes):
    """Vertical cylinders (poles, trunks, a person's body)."""

    center: np.ndarray  # (n, 2) xy of the axis
    radius: np.ndarray  # (n,)
    z0: np.ndarray  # (n,) bottom
    z1: np.ndarray  # (n,) top

    def footprint(self) -> Footprint:
        return self.center, self.radius, self.z0, self.z1


@dataclass
class Ellipsoids(_Shapes):
    """Axis-aligned ellipsoids (foliage, bushes, a head)."""

    center: np.ndarray  # (n, 3)
    radii: np.ndarray  # (n, 3)

    def footprint(self) -> Footprint:
        return (
            self.center[:, :2],
            self.radii[:, :2].max(axis=1),
            self.center[:, 2] - self.radii[:, 2],
            self.center[:, 2] + self.radii[:, 2],
        )


SHAPE_KINDS = (Boxes, Cylinders, Ellipsoids)


@dataclass
class ShapeSet:
    """All primitives of a piece of the world, one struct-of-arrays per kind."""

    parts: dict  # kind -> _Shapes

    @classmethod
    def concat(cls, sets: Iterable[ShapeSet]) -> ShapeSet:
        sets = list(sets)
        return cls({k: k.concat([s.parts[k] for s in sets]) for k in SHAPE_KINDS})

    def __len__(self) -> int:
        return sum(len(p) for p in self.parts.values())


class ShapeBuilder:
    """Collects primitives in route coordinates (s, u, z); `build` places them in the world."""

    def __init__(self) -> None:
        self.rows: dict = {k: [] for k in SHAPE_KINDS}

    def box(
        self,
        s: float,
        u: float,
        z: float,
        half_along: float,
        half_across: float,
        half_z: float,
        label: int,
        instance: int = 0,
        yaw: float = 0.0,
    ) -> None:
        self.rows[Boxes].append((s, u, z, half_along, half_across, half_z, yaw, label, instance))

    def cylinder(
        self, s: float, u: float, radius: float, z0: float, z1: float, label: int, instance: int = 0
    ) -> None:
        self.rows[Cylinders].append((s, u, radius, z0, z1, label, instance))

    def ellipsoid(
        self, s: float, u: float, z: float, r_xy: float, r_z: float, label: int, instance: int = 0
    ) -> None:
        self.rows[Ellipsoids].append((s, u, z, r_xy, r_z, label, instance))

    def build(self, route: Route) -> ShapeSet:
        parts = {}
        for kind, rows in self.rows.items():
            a = np.array(rows, dtype=np.float64).reshape(len(rows), -1 if rows else 9)
            xy, heading = route.place(a[:, 0], a[:, 1]) if rows else (np.zeros((0, 2)), np.zeros(0))
            ids = dict(label=a[:, -2].astype(np.uint32), instance=a[:, -1].astype(np.uint32))
            if kind is Boxes:
                parts[kind] = Boxes(
                    center=np.column_stack([xy, a[:, 2]]),
                    half=a[:, 3:6],
                    yaw=a[:, 6] + heading,
                    **ids,
                )
            elif kind is Cylinders:
                parts[kind] = Cylinders(center=xy, radius=a[:, 2], z0=a[:, 3], z1=a[:, 4], **ids)
            else:
                parts[kind] = Ellipsoids(
                    center=np.column_stack([xy, a[:, 2]]),
                    radii=np.column_stack([a[:, 3], a[:, 3], a[:, 4]]),
                    **ids,
                )
        return ShapeSet(parts)
