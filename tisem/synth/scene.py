"""The procedural street world: a route, the scene along it in 50 m tiles, and two actors.

Everything is laid out in *route coordinates* — `s` metres along the road centreline and `u`
metres to its left — and turned into world coordinates once, when a tile is built. The route
(`tisem.synth.route`) is a chain of straight and circular segments, so points can be projected
back onto it analytically (the ground's class is a function of `u`); the primitives are
`tisem.synth.shapes`.

A tile's content is seeded by (seed, tile id) only, so tiles are built lazily, kept in a small
LRU cache (memory stays bounded however long the drive) and look exactly the same when the
route comes back to them. Ground truth uses SemanticKITTI raw ids.
"""

from __future__ import annotations

import math
import zlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from tisem.synth.route import Route
from tisem.synth.shapes import ShapeBuilder, ShapeSet

# SemanticKITTI raw ids of what the world contains
CAR, MOVING_CAR, PERSON = 10, 252, 30
ROAD, PARKING, SIDEWALK, TERRAIN = 40, 44, 48, 72
BUILDING, FENCE, VEGETATION, TRUNK = 50, 51, 70, 71
POLE, TRAFFIC_SIGN = 80, 81

# instance ids (upper 16 bits of a .label); parked cars get 3.. per (tile, slot)
MOVING_CAR_INSTANCE, PERSON_INSTANCE, FIRST_PARKED_INSTANCE = 1, 2, 3

TILE_M = 50.0  # scene tiles along the route
ROAD_HALF_M = 4.0  # two 3.5 m lanes plus a shoulder
PARKING_W_M = 2.5  # a parking lane, present per tile and side
EGO_LANE_U = -1.75  # right-hand traffic: the ego drives in the right lane
MOVERS_SIDE = 1  # build_tile's sides: 0 at +u (left), 1 at -u (right)
OTHER_LANE_U = 1.75
SPEED_MPS = 10.0  # ~1 m per scan at 10 Hz
LOOP_TURN_RADIUS_M = 150.0
PERSON_RESPAWN_S = 8.0
LOOP_PASS_M = 100.0  # how far the loop drive goes past its start at the end
MIN_LOOP_M = 1000.0


# ----------------------------------------------------------------------------- randomness


def make_rng(seed: int, *keys: int | str) -> np.random.Generator:
    """A generator seeded by (seed, *keys): each tile, scan and purpose gets its own stream,
    so any one of them can be regenerated without replaying the others."""
    return np.random.default_rng(np.random.SeedSequence([_word(seed)] + [_word(k) for k in keys]))


def _word(key: int | str) -> int:
    if isinstance(key, str):
        return zlib.crc32(key.encode())
    key = int(key)
    return 2 * key if key >= 0 else -2 * key - 1  # negative tile ids (behind the start)


# ----------------------------------------------------------------------------- objects


def add_car(b: ShapeBuilder, s: float, u: float, yaw: float, label: int, instance: int) -> None:
    """A car: a body box and a smaller cabin box set back a little (roughly car shaped)."""
    b.box(s, u, 0.65, 2.25, 0.9, 0.5, label, instance, yaw)  # z 0.15-1.15
    b.box(
        s - 0.25 * math.cos(yaw),
        u - 0.25 * math.sin(yaw),
        1.43,
        1.2,
        0.78,
        0.28,
        label,
        instance,
        yaw,
    )  # z 1.15-1.71


def add_tree(b: ShapeBuilder, s: float, u: float, rng: np.random.Generator) -> None:
    """A tree: a trunk cylinder up into a foliage ellipsoid whose bottom is 1.4-3 m high
    (low enough that the beams, which look at most 2 degrees up, see the crowns)."""
    z, r_z = rng.uniform(3.2, 4.5), rng.uniform(1.2, 1.8)
    b.cylinder(s, u, rng.uniform(0.15, 0.28), 0.0, z, TRUNK)
    b.ellipsoid(s, u, z, rng.uniform(1.5, 2.6), r_z, VEGETATION)


# ----------------------------------------------------------------------------- routes


def street_route(seed: int, length_m: float) -> Route:
    """A straight-ish street: straights of 80-250 m joined by gentle 6-18 degree bends.

    Segment k's parameters are the k-th draws of one stream, so a longer street has the
    shorter one as its prefix (scan i does not depend on the number of scans)."""
    rng = make_rng(seed, "street-route")
    segments = [(150.0, 0.0)]
    total = 150.0
    while total < length_m + 300.0:
        radius, angle = rng.uniform(300.0, 900.0), math.radians(rng.uniform(6.0, 18.0))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        straight = rng.uniform(80.0, 250.0)
        segments += [(radius * angle, sign / radius), (straight, 0.0)]
        total += radius * angle + straight
    return Route.from_segments(segments, closed=False)


def loop_length_m(num_scans: int) -> float:
    """Loop perimeter for a drive of num_scans: it ends LOOP_PASS_M past its start (a whole
    number of tiles, so tile ids wrap cleanly), never shorter than MIN_LOOP_M."""
    drive = num_scans * SPEED_MPS * 0.1 - LOOP_PASS_M
    return max(MIN_LOOP_M, math.floor(drive / TILE_M) * TILE_M)


def loop_route(length_m: float) -> Route:
    """A stadium loop starting halfway along its bottom straight: out along a long straight,
    a 180 degree turn, back along the other straight (300 m away, out of sensor range), a
    second turn and home past the start."""
    r = LOOP_TURN_RADIUS_M
    straight = (length_m - 2 * math.pi * r) / 2
    if straight <= 0:
        raise ValueError(f"a loop of {length_m} m is shorter than its two turns")
    turn = (math.pi * r, 1.0 / r)
    return Route.from_segments(
        [(straight / 2, 0.0), turn, (straight, 0.0), turn, (straight / 2, 0.0)], closed=True
    )


def make_route(kind: str, num_scans: int, seed: int) -> Route:
    if kind == "street":
        return street_route(seed, num_scans * SPEED_MPS * 0.1)
    if kind == "loop":
        return loop_route(loop_length_m(num_scans))
    raise ValueError(f"route must be 'street' or 'loop', got {kind!r}")


# ----------------------------------------------------------------------------- tiles

# ground classes across the road, from the centreline out, between a tile's edges
_GROUND_BANDS = (ROAD, PARKING, TERRAIN, SIDEWALK, TERRAIN)


@dataclass
class Tile:
    """One 50 m stretch: its primitives and its ground cross-section per side (0 left, 1 right)."""

    tile_id: int
    shapes: ShapeSet
    # (2, 4) |u| where each ground band ends, per side: road, parking lane (empty when the
    # side has none), grass verge (empty when none), sidewalk; terrain beyond
    edges: np.ndarray


def build_tile(route: Route, seed: int, tile_id: int, movers_lane: bool = False) -> Tile:
    """The content of one tile, from (seed, tile id) alone.

    Across the road, per side: road | parking lane (some tiles) | grass verge (some tiles) |
    sidewalk | fence line | front yard (terrain, bushes, hedges) | buildings, or a park of
    trees. Street lights, signs and street trees stand near the curb (in the verge if there
    is one). Each tile has at least one parking lane, sign and fence, so every class appears
    within a few scans.

    `movers_lane`: the right-hand parking lane is on every tile and holds no parked car, so
    the movers that park and leave there (tisem/synth/movers.py) drive through nothing.
    """
    rng = make_rng(seed, "tile", tile_id)
    s0 = tile_id * TILE_M
    b = ShapeBuilder()
    parking = rng.random(2) < 0.35
    if not parking.any():
        parking[rng.integers(2)] = True
    if movers_lane:
        parking[MOVERS_SIDE] = True
    fence_side, sign_side = rng.integers(2), rng.integers(2)
    curb = np.where(parking, ROAD_HALF_M + PARKING_W_M, ROAD_HALF_M)
    verge = np.where(rng.random(2) < 0.5, rng.uniform(1.5, 3.0, 2), 0.0)
    sidewalk_out = curb + verge + rng.uniform(2.5, 4.0, 2)
    edges = np.column_stack([np.full(2, ROAD_HALF_M), curb, curb + verge, sidewalk_out])
    for side, sigma in enumerate((1.0, -1.0)):
        setback = rng.uniform(3.0, 10.0)  # sidewalk -> building line
        line = sidewalk_out[side] + setback
        park = rng.random() < 0.4
        if parking[side] and not (movers_lane and side == MOVERS_SIDE):
            _parked_cars(b, rng, tile_id, side, s0, sigma * (ROAD_HALF_M + PARKING_W_M / 2))
        # street furniture stands 0.4 m in from the curb; trees in the verge or in pits
        furniture_u = sigma * (curb[side] + 0.4)
        tree_u = sigma * (curb[side] + max(verge[side] / 2, 0.9))
        # a street light per side, staggered so the two sides alternate
        light_s = s0 + (5.0 if side == 0 else 30.0) + rng.uniform(-2, 2)
        b.cylinder(light_s, furniture_u, 0.1, 0.0, rng.uniform(6.0, 8.0), POLE)
        sign_s = s0 + rng.uniform(15.0, 22.0)
        if side == sign_side or rng.random() < 0.3:  # a sign: a thin pole, a plate facing traffic
            b.cylinder(sign_s, furniture_u, 0.04, 0.0, 2.5, POLE)
            b.box(sign_s, furniture_u, 2.15, 0.02, 0.32, 0.32, TRAFFIC_SIGN)
        s = s0 + rng.uniform(2.0, 8.0)
        while s < s0 + TILE_M - 1.0:
            if rng.random() < 0.7 and min(abs(s - light_s), abs(s - sign_s)) > 2.0:
                add_tree(b, s, tree_u, rng)
            s += rng.uniform(8.0, 13.0)
        _fence(b, rng, s0, sigma * (sidewalk_out[side] + 0.2), force=side == fence_side)
        if setback > 3.5 and rng.random() < 0.6:  # a hedge along the front of the yard
            length, h = rng.uniform(8.0, 30.0), rng.uniform(0.9, 1.6)
            b.box(
                s0 + rng.uniform(length / 2, TILE_M - length / 2),
                sigma * (sidewalk_out[side] + 1.2),
                h / 2,
                length / 2,
                0.45,
                h / 2,
                VEGETATION,
            )
        for _ in range(rng.integers(1, 5)):  # bushes in the yard
            b.ellipsoid(
                s0 + rng.uniform(0, TILE_M),
                sigma * (sidewalk_out[side] + rng.uniform(1.0, max(setback - 1.0, 1.5))),
                rng.uniform(0.3, 0.7),
                rng.uniform(0.6, 1.4),
                rng.uniform(0.5, 0.9),
                VEGETATION,
            )
        if park:
            for _ in range(rng.integers(4, 9)):
                add_tree(b, s0 + rng.uniform(0, TILE_M), sigma * (line + rng.uniform(0, 25)), rng)
        else:
            _buildings(b, rng, s0, sigma, line)
    return Tile(tile_id, b.build(route), edges)


def _parked_cars(b, rng, tile_id, side, s0, u):
    s, slot = s0 + rng.uniform(0.0, 3.0), 0
    while s + 4.8 < s0 + TILE_M:
        length = rng.uniform(4.0, 4.8)
        if rng.random() < 0.55:
            instance = FIRST_PARKED_INSTANCE + (tile_id * 32 + side * 16 + slot) % 65000
            add_car(
                b,
                s + length / 2,
                u + rng.uniform(-0.15, 0.15),
                rng.uniform(-0.05, 0.05),
                CAR,
                instance,
            )
        s += length + rng.uniform(0.8, 3.0)
        slot += 1


def _fence(b, rng, s0, u, force):
    """Fence runs along the back of the sidewalk, in 10 m chunks."""
    chunks = rng.random(5) < 0.3
    if force and not chunks.any():
        chunks[rng.integers(5)] = True
    for k in np.flatnonzero(chunks):
        h = rng.uniform(1.0, 1.8)
        b.box(s0 + 10.0 * k + 5.0, u, h / 2, 4.9, 0.03, h / 2, FENCE)


def _buildings(b, rng, s0, sigma, line):
    """Buildings shoulder to shoulder behind the front yards, with gaps (and trees in some)."""
    s = s0 + rng.uniform(0.0, 3.0)
    while s < s0 + TILE_M - 4.0:
        length = min(rng.uniform(10.0, 25.0), s0 + TILE_M - s)
        depth, height = rng.uniform(8.0, 16.0), rng.uniform(5.0, 18.0)
        b.box(
            s + length / 2,
            sigma * (line + depth / 2),
            height / 2,
            length / 2,
            depth / 2,
            height / 2,
            BUILDING,
        )
        gap = rng.uniform(2.0, 8.0)
        if gap > 5.0:
            add_tree(b, s + length + gap / 2, sigma * (line + 3.0), rng)
        s += length + gap


# ----------------------------------------------------------------------------- world


class World:
    """The route, its lazily built tiles (LRU cache) and the two actors, at a given time."""

    def __init__(
        self, seed: int, route: Route, cache_tiles: int = 12, movers_lane: bool = False
    ) -> None:
        self.seed = seed
        self.route = route
        self.movers_lane = movers_lane  # build_tile's: the right parking lane kept for movers
        self.cache_tiles = cache_tiles
        self._tiles: OrderedDict[int, Tile] = OrderedDict()
        self._window: tuple = ((), None)  # last (tile ids, concatenated shapes)

    # --- tiles
    def tile_id(self, s: float) -> int:
        tid = math.floor(float(self.route.wrap(s)) / TILE_M)
        return tid % self.num_tiles if self.route.closed else tid

    @property
    def num_tiles(self) -> int:
        return round(self.route.total_m / TILE_M)

    @property
    def cached_tile_ids(self) -> tuple[int, ...]:
        """The ids of the tiles held in the cache, least recently used first (a read-only
        view: the cache is bounded, and a tile that left it is rebuilt identically)."""
        return tuple(self._tiles)

    def tile(self, tile_id: int) -> Tile:
        tile = self._tiles.pop(tile_id, None)
        if tile is None:
            tile = build_tile(self.route, self.seed, tile_id, self.movers_lane)
        self._tiles[tile_id] = tile
        while len(self._tiles) > self.cache_tiles:
            self._tiles.popitem(last=False)
        return tile

    def static_shapes(self, s: float, reach_m: float) -> ShapeSet:
        """Primitives of every tile within reach_m (along the route) of arc length s."""
        first, last = math.floor((s - reach_m) / TILE_M), math.floor((s + reach_m) / TILE_M)
        ids = range(first, last + 1)
        if self.route.closed:
            ids = dict.fromkeys(i % self.num_tiles for i in ids)
        ids = tuple(ids)
        if self._window[0] != ids:  # consecutive scans mostly share their tiles
            self._window = (ids, ShapeSet.concat(self.tile(i).shapes for i in ids))
        return self._window[1]

    def ground_label(self, xy: np.ndarray, s_hint: float) -> np.ndarray:
        """Raw ground class of world points on the ground plane, from their lateral offset."""
        s, u = self.route.project(xy, s_hint)
        tid = np.floor(s / TILE_M).astype(np.int64)
        if self.route.closed:
            tid %= self.num_tiles
        edges = np.empty((len(xy), 4))
        side = (u < 0).astype(np.int64)
        for t in np.unique(tid):
            m = tid == t
            edges[m] = self.tile(int(t)).edges[side[m]]
        band = (np.abs(u)[:, None] >= edges).sum(axis=1)  # 0 road ... 4 beyond the sidewalk
        return np.array(_GROUND_BANDS, dtype=np.uint32)[band]

    # --- motion
    @staticmethod
    def ego_s(t: float) -> float:
        return SPEED_MPS * t

    def vehicle_pose(self, t: ArrayLike) -> np.ndarray:
        """(n, 4, 4) poses of the ego vehicle (on the ground, x forward) at times t."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        xy, h = self.route.place(SPEED_MPS * t, np.full(len(t), EGO_LANE_U))
        T = np.zeros((len(t), 4, 4))
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(h), -np.sin(h), np.sin(h), np.cos(h)
        T[:, 2, 2] = T[:, 3, 3] = 1.0
        T[:, :2, 3] = xy
        return T

    def actors(self, t: float) -> ShapeSet:
        """The moving car and the walking person at time t.

        The car keeps pace in the other lane, 10-26 m ahead, surging and dropping back (so it
        moves in the world and relative to the ego). The person walks towards the ego along a
        sidewalk (one without parked cars in front of it, where there is one); every 8 s they
        start again 25 m ahead, so the drive meets them however long it is (one person at any
        time).
        """
        b = ShapeBuilder()
        s_car = self.ego_s(t) + 18.0 + 8.0 * math.sin(2 * math.pi * t / 16.0)
        add_car(b, s_car, OTHER_LANE_U, 0.0, MOVING_CAR, MOVING_CAR_INSTANCE)
        t0 = math.floor(t / PERSON_RESPAWN_S) * PERSON_RESPAWN_S
        s_spawn = self.ego_s(t0) + 25.0
        edges = self.tile(self.tile_id(s_spawn)).edges
        side = 0 if edges[1, 1] > ROAD_HALF_M and edges[0, 1] == ROAD_HALF_M else 1
        u_person = (1.0, -1.0)[side] * (edges[side, 2] + 1.3)  # 1.3 m into the sidewalk
        s_person = s_spawn - 1.3 * (t - t0)
        b.cylinder(s_person, u_person, 0.2, 0.0, 1.48, PERSON, PERSON_INSTANCE)
        b.ellipsoid(s_person, u_person, 1.62, 0.11, 0.13, PERSON, PERSON_INSTANCE)
        return b.build(self.route)
