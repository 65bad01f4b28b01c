"""Error counts of a real segmentation network on SemanticKITTI sequence 08, frames 0-4.

Written by benchmarks/noise_calibration.py --write-counts; read by
tisem.synth.profile. Counts only: no points, no labels of any scan."""

RANGE_EDGES_M = (0.0, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 50.0)

# true class -> {predicted class: points}
CONFUSION = {
    "car": {"car": 8171, "motorcycle": 8, "other-vehicle": 10, "road": 112, "parking": 6,
        "sidewalk": 2, "other-ground": 2, "building": 7, "fence": 60, "vegetation": 15, "trunk": 18,
        "terrain": 82, "pole": 93},
    "bicycle": {"car": 1, "bicycle": 2, "motorcycle": 42, "sidewalk": 7, "fence": 1, "pole": 42},
    "person": {"car": 32, "bicycle": 58, "other-vehicle": 17, "building": 18, "fence": 122,
        "vegetation": 196, "trunk": 332, "terrain": 17, "pole": 116},
    "bicyclist": {"pole": 1},
    "road": {"car": 705, "other-vehicle": 22, "road": 103814, "parking": 1320, "sidewalk": 3805,
        "other-ground": 8, "building": 7, "fence": 40, "vegetation": 21, "trunk": 37,
        "terrain": 751, "pole": 133},
    "parking": {"car": 26, "road": 30, "parking": 19, "sidewalk": 217, "terrain": 170, "pole": 1},
    "sidewalk": {"car": 260, "bicycle": 68, "motorcycle": 14, "other-vehicle": 3, "person": 13,
        "road": 1146, "parking": 6927, "sidewalk": 139950, "other-ground": 371, "building": 117,
        "fence": 204, "vegetation": 222, "trunk": 412, "terrain": 9172, "pole": 1327,
        "traffic-sign": 45},
    "other-ground": {"sidewalk": 2, "terrain": 2},
    "building": {"car": 150, "bicycle": 118, "parking": 8, "sidewalk": 117, "other-ground": 1,
        "building": 7838, "fence": 1145, "vegetation": 1061, "trunk": 1061, "terrain": 18,
        "pole": 179, "traffic-sign": 3},
    "fence": {"car": 154, "bicycle": 34, "other-vehicle": 7, "sidewalk": 31, "other-ground": 77,
        "building": 10, "fence": 871, "vegetation": 264, "trunk": 618, "terrain": 920, "pole": 436,
        "traffic-sign": 91},
    "vegetation": {"car": 100, "bicycle": 180, "truck": 98, "other-vehicle": 220, "person": 29,
        "sidewalk": 116, "other-ground": 581, "building": 942, "fence": 582, "vegetation": 90139,
        "trunk": 9721, "terrain": 8037, "pole": 2000, "traffic-sign": 1368},
    "trunk": {"sidewalk": 4, "other-ground": 1, "fence": 9, "vegetation": 1246, "trunk": 18152,
        "terrain": 63, "pole": 403, "traffic-sign": 154},
    "terrain": {"car": 44, "other-vehicle": 125, "person": 67, "road": 54, "parking": 95,
        "sidewalk": 12031, "other-ground": 1162, "building": 109, "fence": 373, "vegetation": 2531,
        "trunk": 5101, "terrain": 118256, "pole": 1189, "traffic-sign": 84},
    "pole": {"car": 38, "sidewalk": 9, "vegetation": 34, "trunk": 523, "terrain": 60, "pole": 1525,
        "traffic-sign": 29},
    "traffic-sign": {"fence": 8, "vegetation": 69, "trunk": 616, "pole": 1148,
        "traffic-sign": 2521},
}

# true class -> per range bin: points inside, points at a class boundary,
# errors inside, errors at a boundary
CELLS = {
    "car": (
        (0, 0, 0, 2065, 5844, 145, 33),
        (0, 0, 0, 56, 342, 87, 14),
        (0, 0, 0, 95, 135, 54, 5),
        (0, 0, 0, 5, 52, 61, 8),
    ),
    "bicycle": (
        (0, 0, 0, 0, 0, 53, 0),
        (0, 0, 0, 0, 0, 40, 2),
        (0, 0, 0, 0, 0, 53, 0),
        (0, 0, 0, 0, 0, 40, 0),
    ),
    "person": (
        (0, 0, 0, 50, 601, 142, 0),
        (0, 0, 0, 3, 96, 16, 0),
        (0, 0, 0, 50, 601, 142, 0),
        (0, 0, 0, 3, 96, 16, 0),
    ),
    "bicyclist": (
        (0, 0, 0, 0, 0, 0, 0),
        (0, 0, 0, 0, 1, 0, 0),
        (0, 0, 0, 0, 0, 0, 0),
        (0, 0, 0, 0, 1, 0, 0),
    ),
    "road": (
        (10508, 55381, 16180, 12612, 9304, 1935, 334),
        (177, 2145, 603, 480, 763, 188, 53),
        (41, 506, 158, 632, 2347, 770, 73),
        (81, 1106, 349, 246, 435, 79, 26),
    ),
    "parking": (
        (0, 0, 0, 0, 0, 155, 148),
        (0, 0, 0, 0, 0, 99, 61),
        (0, 0, 0, 0, 0, 150, 141),
        (0, 0, 0, 0, 0, 95, 58),
    ),
    "sidewalk": (
        (27644, 84770, 19201, 8934, 6200, 3612, 984),
        (604, 4065, 1415, 919, 1110, 633, 160),
        (4908, 3788, 1396, 1882, 2762, 1831, 672),
        (171, 860, 385, 336, 687, 494, 129),
    ),
    "other-ground": (
        (0, 0, 0, 0, 0, 0, 0),
        (0, 2, 0, 0, 2, 0, 0),
        (0, 0, 0, 0, 0, 0, 0),
        (0, 2, 0, 0, 2, 0, 0),
    ),
    "building": (
        (0, 0, 0, 0, 2771, 4205, 4432),
        (0, 0, 0, 0, 61, 194, 36),
        (0, 0, 0, 0, 873, 1207, 1633),
        (0, 0, 0, 0, 18, 110, 20),
    ),
    "fence": (
        (0, 0, 0, 855, 1647, 303, 167),
        (0, 0, 0, 216, 285, 16, 24),
        (0, 0, 0, 650, 1333, 95, 66),
        (0, 0, 0, 216, 255, 7, 20),
    ),
    "vegetation": (
        (0, 3118, 26753, 46471, 14346, 10695, 7855),
        (0, 586, 1673, 1224, 617, 511, 264),
        (0, 1592, 6120, 6329, 2809, 2102, 2270),
        (0, 502, 1039, 542, 272, 212, 185),
    ),
    "trunk": (
        (0, 7867, 7077, 518, 1325, 1524, 380),
        (0, 171, 599, 80, 161, 250, 80),
        (0, 0, 448, 120, 221, 675, 84),
        (0, 4, 57, 26, 75, 139, 31),
    ),
    "terrain": (
        (5993, 56205, 30297, 12222, 15383, 8261, 4665),
        (450, 2473, 2304, 1298, 710, 714, 246),
        (1529, 7356, 3661, 858, 2323, 1665, 1478),
        (308, 1213, 1146, 613, 318, 289, 208),
    ),
    "pole": (
        (293, 943, 66, 10, 281, 195, 0),
        (41, 137, 54, 0, 153, 45, 0),
        (8, 381, 15, 10, 84, 56, 0),
        (11, 37, 18, 0, 48, 25, 0),
    ),
    "traffic-sign": (
        (1164, 2328, 131, 0, 443, 69, 0),
        (22, 58, 11, 0, 77, 59, 0),
        (889, 445, 0, 0, 274, 53, 0),
        (13, 40, 5, 0, 65, 57, 0),
    ),
}

# raw ground-truth id -> {predicted class: points}
RAW_PREDICTIONS = {
    10: {"car": 2656, "other-vehicle": 10, "road": 59, "parking": 3, "sidewalk": 2,
        "other-ground": 2, "building": 7, "fence": 60, "vegetation": 15, "trunk": 18, "terrain": 82,
        "pole": 93},
    30: {"car": 8, "bicycle": 46, "building": 8, "fence": 12, "vegetation": 6, "pole": 57},
    252: {"car": 5515, "motorcycle": 8, "road": 53, "parking": 3},
    253: {"pole": 1},
    254: {"car": 24, "bicycle": 12, "other-vehicle": 17, "building": 10, "fence": 110,
        "vegetation": 190, "trunk": 332, "terrain": 17, "pole": 59},
}
