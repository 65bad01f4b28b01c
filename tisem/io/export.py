"""PLY export of a map, for CloudCompare / MeshLab / Open3D.

Every voxel of the snapshot becomes one vertex at its centre (voxels without evidence too,
with label 0 and probability 0), so the file is the map itself: `len(vertices) == len(snapshot)`.
The vertex element uses the standard names (`x y z`, `red green blue`) so every viewer shows
the SemanticKITTI colours without configuration; the extra scalar properties (`label`,
`raw_label`, `probability`) show up as scalar fields in CloudCompare and can be read back with
`read_ply`. The header carries the voxel size and the class table as comments, so a file found
on its own still says what its numbers mean.
"""

from __future__ import annotations

import os

import numpy as np
from plyfile import PlyData, PlyElement

from tisem.labels import class_colors, class_names, train_to_raw
from tisem.snapshot import MapSnapshot

__all__ = ["write_ply", "read_ply", "ply_comments"]

# position and colour under the names every viewer understands; the scalar fields follow
_VERTEX_DTYPE_BASE = [
    ("x", "<f4"),
    ("y", "<f4"),
    ("z", "<f4"),
    ("red", "u1"),
    ("green", "u1"),
    ("blue", "u1"),
]


def ply_comments(snapshot: MapSnapshot) -> list[str]:
    """Header comments: what made the file, the voxel size, and the class table.

    PLY comments are single lines, so the table is one line per class:
    ``class <train_id> <raw_id> <name>``.
    """
    lines = [
        "tisem semantic map: one vertex per voxel centre",
        f"resolution_m {snapshot.resolution_m!r}",
        f"voxels {len(snapshot)}",
        "label = train id (SemanticKITTI learning_map), raw_label = raw id, "
        "probability = normalised counter of the label",
    ]
    names = class_names()
    raw_ids = train_to_raw(np.arange(len(names)))
    lines += [f"class {i} {int(raw_ids[i])} {name}" for i, name in enumerate(names)]
    return lines


def write_ply(path: str | os.PathLike, snapshot: MapSnapshot, binary: bool = True) -> None:
    """Write the map's voxels as a coloured PLY point cloud.

    Vertices: voxel centres (float32 x y z), uchar red/green/blue from the label's colour,
    `label` (train id, uchar; ushort beyond 255 classes), `raw_label` (uint32 SemanticKITTI raw
    id) and `probability` (float32, the label's normalised counter; 0 without evidence).
    `binary=False` writes ASCII (larger, but diffable).
    """
    num_classes = snapshot.counts.shape[1] if snapshot.counts.ndim == 2 else 0
    names = class_names()
    if num_classes > len(names):
        # colours and raw ids are only defined for the classes of the label space
        raise ValueError(
            f"snapshot has {num_classes} classes; the PLY export knows the "
            f"{len(names)} classes of the label space only"
        )
    labels = snapshot.labels()
    # uchar holds the 20 SemanticKITTI train ids; a wider label space would need ushort
    label_type = "u1" if len(names) <= 256 else "<u2"
    vertex = np.empty(
        len(snapshot),
        dtype=_VERTEX_DTYPE_BASE
        + [("label", label_type), ("raw_label", "<u4"), ("probability", "<f4")],
    )
    centers = snapshot.centers()
    vertex["x"], vertex["y"], vertex["z"] = centers[:, 0], centers[:, 1], centers[:, 2]
    rgb = class_colors()[labels]
    vertex["red"], vertex["green"], vertex["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    vertex["label"] = labels
    vertex["raw_label"] = train_to_raw(labels)
    vertex["probability"] = snapshot.confidence()
    element = PlyElement.describe(vertex, "vertex")
    PlyData([element], text=not binary, byte_order="<", comments=ply_comments(snapshot)).write(
        os.fspath(path)
    )


def read_ply(path: str | os.PathLike) -> dict:
    """Read a PLY written by `write_ply` (or any PLY with a `vertex` element).

    Returns {property name: (N,) array} for every vertex property, plus `"xyz"` ((N, 3) float32)
    and `"comments"` (list of header comment lines, not an array).
    """
    ply = PlyData.read(os.fspath(path))
    if "vertex" not in ply:
        raise ValueError(f"{path}: PLY file has no 'vertex' element")
    data = ply["vertex"].data
    out: dict = {name: np.asarray(data[name]) for name in data.dtype.names}
    out["xyz"] = np.stack([out["x"], out["y"], out["z"]], axis=1)
    out["comments"] = list(ply.comments)
    return out
