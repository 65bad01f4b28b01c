"""What a saved map may hold: the checks `Mapper.restore` runs on a state and a snapshot
(from a checkpoint or a map file) before anything is built from them.

A saved file can pass its own integrity checks and still hold values no mapper wrote (a scan
count of "abc", a NaN counter, a key beyond the store's range): each is refused here with one
ValueError naming the key and the value, and the mapper stays empty.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from tisem.class_centroids import centroid_problem
from tisem.map_clock import MAX_MAP_SECONDS, MapClock
from tisem.poses import MAX_POSITION_M
from tisem.snapshot import MapSnapshot
from tisem.store import KEY_LIMIT


@dataclass
class SavedState:
    """A mapper's state (`Mapper.state()`), checked; origin_vox None: nothing was mapped."""

    origin_vox: np.ndarray | None
    center_vox: np.ndarray
    scans: int = 0
    last_stamp_s: float | None = None
    clock: MapClock | None = None


def _integer(value, key: str, lo: int, hi: int) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, (numbers.Integral, np.integer))
        or not lo <= int(value) <= hi
    ):
        raise ValueError(
            f"mapper state: {key} must be a whole number in [{lo}, {hi}], got {value!r}"
        )
    return int(value)


def _finite(value, key: str) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, (numbers.Real, np.number))
        or not math.isfinite(float(value))
    ):
        raise ValueError(f"mapper state: {key} must be a finite number, got {value!r}")
    return float(value)


def _vector(value, key: str, limit: int) -> np.ndarray:
    if not isinstance(value, (list, tuple, np.ndarray)) or len(value) != 3:
        raise ValueError(f"mapper state: {key} must be 3 whole numbers, got {value!r}")
    return np.array(
        [_integer(v, f"{key}[{a}]", -limit, limit) for a, v in enumerate(value)], np.int64
    )


def parse_state(state, resolution_m: float, decay_tau_s: float) -> SavedState:
    """The checked state; ValueError naming the first bad key."""
    if not isinstance(state, dict):
        raise ValueError(f"mapper state must be a mapping, got {type(state).__name__}")
    if state.get("origin_vox") is None:
        return SavedState(None, np.zeros(3, np.int64))
    origin = _vector(state["origin_vox"], "origin_vox", int(MAX_POSITION_M / resolution_m) + 1)
    center = state.get("center_vox")
    center = np.zeros(3, np.int64) if center is None else _vector(center, "center_vox", KEY_LIMIT)
    scans = _integer(state.get("scans", 0), "scans", 0, 2**62)
    last = state.get("last_stamp_s")
    last = None if last is None else _finite(last, "last_stamp_s")
    t0 = _finite(state.get("t0"), "t0")
    saved_clock = state.get("clock")
    if saved_clock is None:  # a state saved before the map kept a clock of its own
        saved_clock = {"t0": t0, "latest_s": 0.0 if last is None else last - t0}
    if not isinstance(saved_clock, dict):
        raise ValueError(f"mapper state: clock must be a mapping, got {saved_clock!r}")
    clock = MapClock.from_dict(decay_tau_s, saved_clock)
    if clock.state.t0 != t0:
        raise ValueError(f"mapper state: t0 {t0!r} differs from the clock's {clock.state.t0!r}")
    return SavedState(origin, center, scans, last, clock)


def check_snapshot(snapshot: MapSnapshot, num_classes: int, resolution_m: float) -> None:
    """ValueError unless the snapshot's arrays fit a map of this size: shapes that agree,
    finite counters >= 0, finite times, kernel lengths > 0."""
    if not math.isfinite(snapshot.resolution_m) or abs(snapshot.resolution_m - resolution_m) > 1e-9:
        raise ValueError(
            f"snapshot resolution {snapshot.resolution_m} m != mapper {resolution_m} m"
        )
    n = len(snapshot.keys)
    shapes = {"keys": (n, 3), "counts": (n, num_classes), "t_last": (n,), "ell_m": (n,)}
    for name, shape in shapes.items():
        got = np.shape(getattr(snapshot, name))
        if got != shape:
            what = "classes" if name == "counts" and len(got) == 2 and got[0] == n else "shape"
            raise ValueError(
                f"snapshot {name} has shape {got}, expected {shape}"
                + (f" (the mapper has {num_classes} classes)" if what == "classes" else "")
            )
    for name, ok in (
        ("counts", lambda a: np.isfinite(a) & (a >= 0)),
        ("t_last", np.isfinite),
        ("ell_m", lambda a: np.isfinite(a) & (a > 0)),
    ):
        a = np.asarray(getattr(snapshot, name))
        if a.dtype.kind not in "iuf":
            raise ValueError(f"snapshot {name} must be numbers, got dtype {a.dtype}")
        good = ok(a)
        if not good.all():
            i = np.unravel_index(int(np.flatnonzero(~good.ravel())[0]), a.shape)
            raise ValueError(
                f"snapshot {name} holds {a[i].item()!r} at "
                f"{tuple(int(k) for k in i)}: "
                f"counters must be finite and >= 0, times finite, lengths > 0"
            )
    if np.asarray(snapshot.keys).dtype.kind not in "iu":
        raise ValueError(f"snapshot keys must be integers, got dtype {snapshot.keys.dtype}")
    if snapshot.centroids is not None:
        problem = centroid_problem(np.asarray(snapshot.centroids), n, num_classes)
        if problem is not None:
            raise ValueError(f"snapshot {problem}")


def relative_arrays(snapshot: MapSnapshot, saved: SavedState) -> tuple:
    """The snapshot's voxels as the store keeps them: (keys relative to the saved origin,
    counts, t_last_rel, length_m); ValueError for keys or times a map cannot hold."""
    keys = np.asarray(snapshot.keys, np.int64) - saved.origin_vox
    if len(keys) and np.abs(keys).max() > KEY_LIMIT:
        raise ValueError(
            f"snapshot keys reach {np.abs(keys).max()} voxels from the saved "
            f"origin; a map holds at most {KEY_LIMIT}"
        )
    t_rel = np.asarray(snapshot.t_last, np.float64) - saved.clock.state.t0
    if len(t_rel) and np.abs(t_rel).max() > MAX_MAP_SECONDS:
        raise ValueError(
            f"snapshot t_last reaches {np.abs(t_rel).max():.6g} s from the saved "
            f"t0; a map spans at most {MAX_MAP_SECONDS:.0f} s"
        )
    return (
        keys,
        np.asarray(snapshot.counts, np.float32),
        t_rel.astype(np.float32),
        np.asarray(snapshot.ell_m, np.float32),
    )
