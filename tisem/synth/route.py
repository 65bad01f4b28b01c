"""The road the synthetic world is laid along: straight and circular segments by arc length.

Route coordinates are `s` metres along the centreline and `u` metres to its left. Because
every segment is a line or an arc, points are placed in the world and projected back onto the
route analytically.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


@dataclass
class Route:
    """A chain of straight (kappa 0) and circular segments, parametrised by arc length s.

    An open route (the street) extends its first and last segments beyond its ends; a
    closed one (the loop) wraps s modulo its length.
    """

    s0: np.ndarray  # (k,) arc length at each segment start
    length: np.ndarray  # (k,)
    start: np.ndarray  # (k, 2) xy at each segment start
    heading0: np.ndarray  # (k,)
    kappa: np.ndarray  # (k,) signed curvature, > 0 turns left
    closed: bool

    @classmethod
    def from_segments(cls, segments: Iterable[tuple[float, float]], closed: bool) -> Route:
        """segments: [(length, kappa)], starting at the origin heading along +x."""
        s0, xy, h = [], [np.zeros(2)], [0.0]
        s = 0.0
        for length, kappa in segments:
            s0.append(s)
            end, hend = _segment_point(xy[-1], h[-1], kappa, length)
            xy.append(end)
            h.append(hend)
            s += length
        return cls(
            np.array(s0),
            np.array([m for m, _ in segments], dtype=np.float64),
            np.array(xy[:-1]),
            np.array(h[:-1]),
            np.array([k for _, k in segments], dtype=np.float64),
            closed,
        )

    @property
    def total_m(self) -> float:
        return float(self.s0[-1] + self.length[-1])

    def wrap(self, s: ArrayLike) -> np.ndarray:
        return np.mod(s, self.total_m) if self.closed else np.asarray(s, dtype=np.float64)

    def frame(self, s: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Centreline xy (n, 2) and heading (n,) at arc lengths s."""
        s = self.wrap(np.atleast_1d(np.asarray(s, dtype=np.float64)))
        i = np.clip(np.searchsorted(self.s0, s, side="right") - 1, 0, len(self.s0) - 1)
        return _segment_point(self.start[i], self.heading0[i], self.kappa[i], s - self.s0[i])

    def place(self, s: ArrayLike, u: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """World xy (n, 2) and heading (n,) of route coordinates (s, u)."""
        xy, h = self.frame(s)
        return xy + np.asarray(u)[:, None] * np.column_stack([-np.sin(h), np.cos(h)]), h

    def project(
        self, xy: np.ndarray, s_hint: float, reach_m: float = 250.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Route coordinates (s, u) of world points near arc length `s_hint`.

        Each candidate segment gives its own (s, u); the one whose foot point is closest wins.
        Headings are continuous across segment joints, so every point (closer than a turn
        radius) lies in the span of some segment.
        """
        if self.closed:
            cand = np.arange(len(self.s0))
        else:
            cand = np.flatnonzero(
                (self.s0 + self.length > s_hint - reach_m) & (self.s0 < s_hint + reach_m)
            )
            if cand.size == 0:
                cand = np.array([0 if s_hint < 0 else len(self.s0) - 1])
        best = np.full(len(xy), np.inf)
        s_out = np.zeros(len(xy))
        u_out = np.zeros(len(xy))
        last = len(self.s0) - 1
        for j in cand:
            t, u = _segment_local(
                xy, self.start[j], self.heading0[j], self.kappa[j], self.length[j]
            )
            lo = -np.inf if (j == 0 and not self.closed) else 0.0
            hi = np.inf if (j == last and not self.closed) else self.length[j]
            dist = np.hypot(t - np.clip(t, lo, hi), u)
            better = dist < best
            best[better] = dist[better]
            s_out[better] = self.s0[j] + t[better]
            u_out[better] = u[better]
        return self.wrap(s_out), u_out


def _segment_point(start, heading0, kappa, t):
    """Position and heading after arc length t along a segment (vectorised)."""
    kappa = np.asarray(kappa, dtype=np.float64)
    h = heading0 + kappa * t
    straight = kappa == 0
    k = np.where(straight, 1.0, kappa)
    dx = np.where(straight, t * np.cos(heading0), (np.sin(h) - np.sin(heading0)) / k)
    dy = np.where(straight, t * np.sin(heading0), (np.cos(heading0) - np.cos(h)) / k)
    return np.asarray(start) + np.stack([dx, dy], axis=-1), h


def _segment_local(xy, start, heading0, kappa, length):
    """(t along, u left) of points relative to one segment, t unclamped."""
    if kappa == 0:
        rel = xy - start
        c, s = math.cos(heading0), math.sin(heading0)
        return rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
    # the centre of the arc is on the left for kappa > 0; the foot point's normal points
    # from the query point to the centre (times sign(kappa))
    centre = start + np.array([-math.sin(heading0), math.cos(heading0)]) / kappa
    w = centre - xy
    rho = np.hypot(w[:, 0], w[:, 1])
    n = math.copysign(1.0, kappa) * w / np.maximum(rho, 1e-9)[:, None]
    h = np.arctan2(-n[:, 0], n[:, 1])
    # pick the branch of the angle nearest the segment's middle
    half = 0.5 * length
    dh = np.mod(h - heading0 - kappa * half + np.pi, 2 * np.pi) - np.pi
    return half + dh / kappa, math.copysign(1.0, kappa) * (1.0 / abs(kappa) - rho)
