"""A label space other than SemanticKITTI's, read from a YAML file.

The file has the keys of SemanticKITTI's own `semantic-kitti.yaml`, so that file and any copy
edited for another data set both work::

    labels:            {0: unlabeled, 10: car, 40: road, 70: vegetation}   # raw id -> name
    color_map:         {0: [0, 0, 0], 10: [245, 150, 100], ...}             # raw id -> BGR
    learning_map:      {0: 0, 10: 1, 40: 2, 70: 3}                          # raw id -> train id
    learning_map_inv:  {0: 0, 1: 10, 2: 40, 3: 70}                          # train id -> raw id

`num_classes` is the number of train ids (the largest + 1); train id 0 is "unlabeled" (not
scored). `learning_map_inv` may be left out when every train id has one raw id. Colours are
BGR as in semantic-kitti.yaml, or RGB under the key `color_map_rgb`. A mistake is one
`ValueError` naming the file and the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

__all__ = ["LabelSpace", "load_label_space"]

RAW_IDS = 1 << 16  # a .label file's semantic id is its lower 16 bits


@dataclass(frozen=True)
class LabelSpace:
    """Train ids 0..num_classes-1 with their names, RGB colours and raw ids, and the map from
    raw ids to train ids."""

    names: tuple[str, ...]
    colors_rgb: np.ndarray  # (C, 3) uint8
    learning_map: dict[int, int]  # raw id -> train id
    learning_map_inv: np.ndarray  # (C,) uint32 train id -> raw id
    source: str = ""
    lookup: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        to_train = np.zeros(RAW_IDS, dtype=np.int32)
        known = np.zeros(RAW_IDS, dtype=bool)
        for raw, train in self.learning_map.items():
            to_train[raw], known[raw] = train, True
        object.__setattr__(self, "lookup", (to_train, known))

    @property
    def num_classes(self) -> int:
        return len(self.names)


def _int_map(data: dict, key: str, where: str, values: type = int) -> dict:
    table = data.get(key)
    if not isinstance(table, dict) or not table:
        raise ValueError(f"{where}: '{key}' must be a mapping (id: value), got {table!r}")
    out = {}
    for k, v in table.items():
        if not isinstance(k, int) or isinstance(k, bool) or not 0 <= k < RAW_IDS:
            raise ValueError(f"{where}: '{key}': key {k!r} is not an id in 0..{RAW_IDS - 1}")
        out[k] = v
    return out


def load_label_space(path: str | Path) -> LabelSpace:
    """The label space of a semantic-kitti.yaml-style file (module docstring)."""
    where = str(path)
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{where}: cannot read the class file: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a mapping with labels, color_map, learning_map")
    names_raw = _int_map(data, "labels", where)
    learning = _int_map(data, "learning_map", where)
    for raw, train in learning.items():
        if not isinstance(train, int) or isinstance(train, bool) or train < 0:
            raise ValueError(
                f"{where}: 'learning_map': raw id {raw} -> {train!r}; expected a train id >= 0"
            )
    num_classes = max(learning.values()) + 1
    if num_classes < 2:
        raise ValueError(f"{where}: 'learning_map' has no train id above 0 (unlabeled)")
    if "learning_map_inv" in data:
        inv = _int_map(data, "learning_map_inv", where)
        missing = sorted(set(range(num_classes)) - set(inv))
        if missing or len(inv) != num_classes:
            raise ValueError(
                f"{where}: 'learning_map_inv' must name one raw id for each train "
                f"id 0..{num_classes - 1}"
                + (f"; missing {missing}" if missing else f"; it has {len(inv)} entries")
            )
    else:
        inv = {}
        for raw, train in sorted(learning.items()):
            inv.setdefault(train, raw)
        missing = sorted(set(range(num_classes)) - set(inv))
        if missing:
            raise ValueError(f"{where}: 'learning_map' maps no raw id to train ids {missing}")
    for train, raw in inv.items():
        if raw not in names_raw:
            raise ValueError(f"{where}: 'labels' has no name for raw id {raw} (train id {train})")
    bgr = "color_map" in data
    colors = _int_map(data, "color_map" if bgr else "color_map_rgb", where)
    rgb = np.zeros((num_classes, 3), dtype=np.uint8)
    for train in range(num_classes):
        color = colors.get(inv[train])
        if not (
            isinstance(color, list)
            and len(color) == 3
            and all(isinstance(c, int) and 0 <= c <= 255 for c in color)
        ):
            raise ValueError(
                f"{where}: colour of raw id {inv[train]}: expected 3 numbers 0..255, got {color!r}"
            )
        rgb[train] = color[::-1] if bgr else color
    return LabelSpace(
        names=tuple(str(names_raw[inv[t]]) for t in range(num_classes)),
        colors_rgb=rgb,
        learning_map=dict(learning),
        learning_map_inv=np.array([inv[t] for t in range(num_classes)], dtype=np.uint32),
        source=where,
    )
