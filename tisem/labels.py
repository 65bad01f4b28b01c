"""The label space: raw ids, train ids, names and colours (SemanticKITTI's 20 classes, or one
read from a YAML file).

Raw ids are what `.label` files store (lower 16 bits); train ids are the classes the network
predicts and the map stores (0 = unlabeled / ignored). The two are kept apart in every name in
tisem: `raw_label` vs `train_id`. The constants below are SemanticKITTI's; `raw_to_train`,
`train_to_raw`, `class_names` and `class_colors` follow the active label space, which a run
given `--classes FILE` sets (`use_label_space`, tisem/label_space.py).
"""

from __future__ import annotations

import logging

import numpy as np

NUM_CLASSES = 20  # train ids 0..19, 0 = unlabeled

# semantic-kitti.yaml `learning_map` (raw id -> train id)
LEARNING_MAP: dict[int, int] = {
    0: 0,
    1: 0,
    10: 1,
    11: 2,
    13: 5,
    15: 3,
    16: 5,
    18: 4,
    20: 5,
    30: 6,
    31: 7,
    32: 8,
    40: 9,
    44: 10,
    48: 11,
    49: 12,
    50: 13,
    51: 14,
    52: 0,
    60: 9,
    70: 15,
    71: 16,
    72: 17,
    80: 18,
    81: 19,
    99: 0,
    252: 1,
    253: 7,
    254: 6,
    255: 8,
    256: 5,
    257: 5,
    258: 4,
    259: 5,
}

# semantic-kitti.yaml `learning_map_inv` (train id -> raw id)
LEARNING_MAP_INV = np.array(
    [0, 10, 11, 15, 18, 20, 30, 31, 32, 40, 44, 48, 49, 50, 51, 70, 71, 72, 80, 81], dtype=np.uint32
)

CLASS_NAMES: tuple[str, ...] = (
    "unlabeled",
    "car",
    "bicycle",
    "motorcycle",
    "truck",
    "other-vehicle",
    "person",
    "bicyclist",
    "motorcyclist",
    "road",
    "parking",
    "sidewalk",
    "other-ground",
    "building",
    "fence",
    "vegetation",
    "trunk",
    "terrain",
    "pole",
    "traffic-sign",
)

# the classes that move (train ids): car, bicycle, motorcycle, truck, other-vehicle, person,
# bicyclist, motorcyclist; they may take a shorter tau (MapperConfig.tau_movable_s)
MOVABLE_CLASSES: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8)
# SemanticKITTI's raw ids of moving objects (moving-car ... moving-other-vehicle)
MOVING_RAW_IDS = (252, 259)  # inclusive range


def moving_raw(raw: np.ndarray) -> np.ndarray:
    """(N,) bool: which raw SemanticKITTI labels (lower 16 bits) mark a moving object."""
    sem = np.asarray(raw) & 0xFFFF
    return (sem >= MOVING_RAW_IDS[0]) & (sem <= MOVING_RAW_IDS[1])


# semantic-kitti.yaml `color_map` is BGR; these are the same colours as RGB, per train id.
CLASS_COLORS_RGB = np.array(
    [
        [0, 0, 0],
        [100, 150, 245],
        [100, 230, 245],
        [30, 60, 150],
        [80, 30, 180],
        [0, 0, 255],
        [255, 30, 30],
        [255, 40, 200],
        [150, 30, 90],
        [255, 0, 255],
        [255, 150, 255],
        [75, 0, 75],
        [175, 0, 75],
        [255, 200, 0],
        [255, 120, 50],
        [0, 175, 0],
        [135, 60, 0],
        [150, 240, 80],
        [255, 240, 150],
        [255, 0, 0],
    ],
    dtype=np.uint8,
)

# Lookup table over the whole 16-bit raw space; ids not in LEARNING_MAP map to 0 and are
# flagged by `raw_known` so readers can count and report them.
_RAW_TO_TRAIN = np.zeros(1 << 16, dtype=np.int32)
_RAW_KNOWN = np.zeros(1 << 16, dtype=bool)
for _raw, _train in LEARNING_MAP.items():
    _RAW_TO_TRAIN[_raw] = _train
    _RAW_KNOWN[_raw] = True


def raw_to_train(raw_label: np.ndarray) -> tuple[np.ndarray, int]:
    """Map raw labels (instance bits allowed) to train ids of the active label space.

    Returns (train_id int32, number of points whose raw id is unknown -> 0).
    """
    semantic = np.asarray(raw_label).astype(np.uint32) & 0xFFFF
    to_train, known = (_RAW_TO_TRAIN, _RAW_KNOWN) if _active is None else _active.lookup
    train_id = to_train[semantic]
    unknown = int(np.count_nonzero(~known[semantic]))
    return train_id, unknown


LABEL_SPACES = ("auto", "raw", "train")


def label_space_of(values: np.ndarray) -> str:
    """Which ids label values are: "train" (every value below num_classes(), no instance bits
    either, and one at least no raw id of the label space), "either" (every value below
    num_classes() and a raw id: a scan without a class that only train ids name), or "raw".

    A scan in raw SemanticKITTI ids holds ground, whose ids are all past 19 (road 40, sidewalk
    48, terrain 72), and the raw ids below 20 (unlabeled, outlier and the vehicles) are known
    ones; a network's argmax saved without the inverse learning map holds 0..19, among them
    ids that name no raw class (9, road, is the most common)."""
    values = np.asarray(values)
    if values.size == 0 or values.min() < 0 or values.max() >= num_classes():
        return "raw"
    known = _RAW_KNOWN if _active is None else _active.lookup[1]
    return "either" if known[values.astype(np.int64)].all() else "train"


# files or clouds a reader looks through for the first that decides the space of its values
# that fit both: a bound on the search where none decides (a field of zeros, say)
SPACE_SEARCH_LIMIT = 200


def deciding_space(values: np.ndarray) -> str | None:
    """The space label values decide, "raw" or "train" (`label_space_of`), or None where they
    decide none: no values, or values that fit both."""
    values = np.asarray(values)
    if values.size == 0:
        return None
    space = label_space_of(values)
    return None if space == "either" else space


def read_alike(values: np.ndarray) -> bool:
    """Whether values that fit both spaces give the same train ids read either way (unlabeled
    0 only, say, or a label space whose raw ids below its class count are its train ids): then
    no space needs deciding."""
    values = np.asarray(values).astype(np.int64)
    return bool(np.array_equal(raw_to_train(values)[0], values))


def holds_train_ids(values: np.ndarray) -> bool:
    """Whether label values can only be train ids (`label_space_of`)."""
    return label_space_of(values) == "train"


def to_train_ids(
    values: np.ndarray,
    label_space: str = "auto",
    classes: int | None = None,
    either: str = "raw",
) -> tuple[np.ndarray, int, str]:
    """(train ids int32, how many values are no label of the space (they become 0: no
    evidence), the space they were read in: "raw" or "train").

    `label_space`: "raw" (SemanticKITTI ids, instance bits allowed: `raw_to_train`), "train"
    (0..classes - 1, num_classes() by default), or "auto": by `label_space_of`, values that
    can be either read as `either` (the space the reader decided for its source: that of the
    source's first file or cloud that fits one)."""
    if label_space not in LABEL_SPACES:
        raise ValueError(f"label_space must be one of {LABEL_SPACES}, got {label_space!r}")
    if label_space == "auto":
        found = label_space_of(values)
        label_space = either if found == "either" else found
    if label_space == "raw":
        return (*raw_to_train(values), "raw")
    values = np.asarray(values).astype(np.int64)
    bad = (values < 0) | (values >= (num_classes() if classes is None else classes))
    return np.where(bad, 0, values).astype(np.int32), int(np.count_nonzero(bad)), "train"


class TrainIdNotes:
    """Per label source of a reader (the predictions, the ground truth): whether `to_train_ids`
    read it as train ids, said once in a warning (a run on labels in the other space is
    otherwise silently wrong everywhere). Which space values that fit both are read in is the
    reader's to say: that of the source's first file or cloud that fits one."""

    def __init__(self, log: logging.Logger) -> None:
        self.log = log
        self.sources: dict[str, int] = {}  # label source -> scans read as train ids
        self.lines: list[str] = []  # what was said

    def read(self, source: str, where: str, space: str) -> None:
        if space != "train":
            return
        if source not in self.sources:
            self.lines.append(
                f"{where}: the {source} are train ids, not raw SemanticKITTI ids (all their "
                f"values below {num_classes()}, and some, here or in another scan of them, "
                f"naming no raw class): read as train ids, here and in every scan of them "
                f"whose values can be"
            )
            self.log.warning("%s", self.lines[-1])
        self.sources[source] = self.sources.get(source, 0) + 1


def train_to_raw(train_id: np.ndarray) -> np.ndarray:
    """Map train ids to raw ids (uint32), as SemanticKITTI predictions store them."""
    train_id = np.asarray(train_id)
    to_raw = LEARNING_MAP_INV if _active is None else _active.learning_map_inv
    if train_id.size and (train_id.min() < 0 or train_id.max() >= to_raw.size):
        raise ValueError(
            f"train ids must lie in [0, {to_raw.size}), got [{train_id.min()}, {train_id.max()}]"
        )
    return to_raw[train_id]


def num_classes() -> int:
    """Train ids of the active label space (0 = unlabeled included)."""
    return NUM_CLASSES if _active is None else _active.num_classes


def class_names() -> tuple[str, ...]:
    """The names of the active label space, per train id."""
    return CLASS_NAMES if _active is None else _active.names


def class_colors() -> np.ndarray:
    """(C, 3) uint8 RGB colours of the active label space, per train id."""
    return CLASS_COLORS_RGB if _active is None else _active.colors_rgb


def class_table() -> list[dict]:
    """The class table as plain records (for metadata in exported files)."""
    raw = LEARNING_MAP_INV if _active is None else _active.learning_map_inv
    names, colors = class_names(), class_colors()
    return [
        {"train_id": i, "raw_id": int(raw[i]), "name": names[i], "rgb": [int(c) for c in colors[i]]}
        for i in range(num_classes())
    ]


_active = None  # a LabelSpace; None: SemanticKITTI's


def use_label_space(space) -> None:
    """Make `space` (a `tisem.label_space.LabelSpace`, or None for SemanticKITTI's) the label
    space of everything that reads or writes labels in this process."""
    global _active
    _active = space
