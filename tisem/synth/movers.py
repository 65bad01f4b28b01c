"""More movers for the synthetic street, whose ground truth knows what is dynamic.

Beside the street's own moving car and walking person (`World.actors`): oncoming cars, a
cyclist, a group of pedestrians, a car that arrives and parks, and one that leaves its parking
spot (the hard case: static for a while, then gone). The last two use the right parking lane,
which the street then keeps free of parked cars, so that no mover drives through anything.
Every mover has a position per time; a point on it is dynamic when the mover is under way, or
not where it was by the end of the drive (more than `STILL_M` away), which is what a static
map must then not hold: the parking car's points once it has stopped are static, the leaving
car's points dynamic from the first scan, and a mover still under way at the end is dynamic in
its last scan too.

    movers = StreetMovers(world)
    shapes = movers.shapes(t)                     # ShapeSet of the movers at time t
    dynamic = movers.dynamic(instance, t, t_end)  # (N,) bool per point, from its instance id
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tisem.synth.scene import (
    EGO_LANE_U,
    OTHER_LANE_U,
    PARKING_W_M,
    ROAD_HALF_M,
    SPEED_MPS,
    World,
    add_car,
)
from tisem.synth.shapes import ShapeBuilder, ShapeSet

CAR, BICYCLIST, PERSON = 10, 31, 30  # raw ids (their static classes: motion is the flag)
FIRST_INSTANCE = 1000  # instance ids of the movers (the street's are below)
STILL_M = 0.5
PARKING_U = -(ROAD_HALF_M + PARKING_W_M / 2)


@dataclass(frozen=True)
class Mover:
    """One mover: kind ('car', 'cyclist', 'person'), lateral offset u, and its route position
    s(t) = s0 + speed * clamp(t - t_start, 0, t_stop - t_start) (it stands before t_start and
    after t_stop); `period_s` > 0 respawns it every period (s0 relative to the ego then)."""

    kind: str
    u: float
    s0: float
    speed: float
    t_start: float = 0.0
    t_stop: float = math.inf
    period_s: float = 0.0

    def moving(self, t: float) -> bool:
        """Whether it is under way at time t."""
        if self.speed == 0:
            return False
        return self.period_s > 0 or self.t_start <= t < self.t_stop

    def s(self, t: float) -> float:
        if self.period_s > 0:
            t0 = math.floor(t / self.period_s) * self.period_s
            return SPEED_MPS * t0 + self.s0 + self.speed * (t - t0)
        return self.s0 + self.speed * min(max(t - self.t_start, 0.0), self.t_stop - self.t_start)


def street_movers() -> tuple[Mover, ...]:
    """The movers of the street (route positions in metres from its start)."""
    return (
        Mover("car", OTHER_LANE_U + 0.3, 70.0, -9.0, period_s=7.0),  # oncoming, respawned
        Mover("cyclist", EGO_LANE_U - 1.6, 12.0, 6.0),  # ahead, slower
        *(
            Mover("person", ROAD_HALF_M + 1.2 + 0.7 * (i % 2), 35.0 + 0.8 * i, -1.2)
            for i in range(3)
        ),  # a group on the walk
        # arrives along the right parking lane (kept free of parked cars: World's movers_lane)
        # and parks 1 m behind the car that leaves its spot at 3 s and drives on along it
        Mover("car", PARKING_U, -12.5, 7.0, t_start=0.0, t_stop=5.0),  # parks at 22.5 m
        Mover("car", PARKING_U, 28.0, 6.0, t_start=3.0),
    )


class StreetMovers:
    """The movers of one synthetic world."""

    def __init__(self, world: World, movers: tuple[Mover, ...] | None = None):
        self.world = world
        self.movers = street_movers() if movers is None else movers

    def shapes(self, t: float) -> ShapeSet:
        b = ShapeBuilder()
        for i, m in enumerate(self.movers):
            inst, s = FIRST_INSTANCE + i, m.s(t)
            if m.kind == "car":
                add_car(b, s, m.u, 0.0 if m.speed >= 0 else math.pi, CAR, inst)
            elif m.kind == "cyclist":
                b.box(s, m.u, 0.55, 0.85, 0.25, 0.4, BICYCLIST, inst)
                b.cylinder(s, m.u, 0.22, 0.95, 1.75, BICYCLIST, inst)
            else:
                b.cylinder(s, m.u, 0.2, 0.0, 1.48, PERSON, inst)
                b.ellipsoid(s, m.u, 1.62, 0.11, 0.13, PERSON, inst)
        return b.build(self.world.route)

    def dynamic(self, instance: np.ndarray, t: float, t_end: float) -> np.ndarray:
        """(N,) bool: points on a mover that is under way at t (as SemanticKITTI's moving
        labels have it), or that is elsewhere (> STILL_M) at t_end than at t (it parked, and
        left by the end)."""
        moved = np.array([m.moving(t) or abs(m.s(t) - m.s(t_end)) > STILL_M for m in self.movers])
        idx = instance.astype(np.int64) - FIRST_INSTANCE
        mine = (idx >= 0) & (idx < len(self.movers))
        out = np.zeros(len(instance), bool)
        out[mine] = moved[idx[mine]]
        return out
