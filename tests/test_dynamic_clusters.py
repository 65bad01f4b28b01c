"""Spreading free space's dynamic flags over movable-class clusters (tisem/dynamic_clusters.py):
the groups of touching cells against a breadth-first search, and analytic scenes whose flags are
known."""

import itertools

import numpy as np
import pytest

from tisem.dynamic_clusters import clusters, spread_over_clusters

CAR, ROAD, POLE = 1, 9, 18
MOVABLE = np.zeros(20, bool)
MOVABLE[1:9] = True


def bfs_groups(cells: np.ndarray) -> list[set[tuple]]:
    """The groups of touching cells (26-neighbours), by breadth-first search."""
    todo = {tuple(c) for c in cells.tolist()}
    groups = []
    while todo:
        start = todo.pop()
        group, frontier = {start}, [start]
        while frontier:
            c = frontier.pop()
            for off in itertools.product((-1, 0, 1), repeat=3):
                n = (c[0] + off[0], c[1] + off[1], c[2] + off[2])
                if n in todo:
                    todo.remove(n)
                    group.add(n)
                    frontier.append(n)
        groups.append(group)
    return groups


@pytest.mark.parametrize("seed", range(5))
def test_clusters_match_a_breadth_first_search(seed):
    rng = np.random.default_rng(seed)
    cells = rng.integers(-6, 6, size=(300, 3))  # sparse enough for many groups
    distinct, group, of_input = clusters(cells)
    assert np.array_equal(distinct[of_input], cells)
    found = {}
    for c, g in zip(distinct.tolist(), group.tolist()):
        found.setdefault(g, set()).add(tuple(c))
    expected = bfs_groups(cells)
    assert len(expected) > 3
    assert sorted(map(sorted, found.values())) == sorted(map(sorted, expected))


def box_points(lo, hi, step=0.1):
    axes = [np.arange(a, b, step) + step / 2 for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def scene(car_a_x=0.0):
    """Car A (a 2 x 1 x 1 m box at x = car_a_x), car B 3 m away, a pole 2 m from A, and
    three points inside A that the network calls pole."""
    a = box_points((car_a_x, 0, 0), (car_a_x + 2, 1, 1))
    b = box_points((5, 0, 0), (7, 1, 1))
    pole = box_points((car_a_x - 2.2, 0, 0), (car_a_x - 2.0, 0.2, 2))
    points = np.concatenate([a, b, pole])
    labels = np.r_[np.full(len(a), CAR), np.full(len(b), CAR), np.full(len(pole), POLE)]
    labels[[10, 20, 30]] = POLE  # parts of A the network calls pole
    parts = {"a": np.arange(len(a)), "b": len(a) + np.arange(len(b))}
    parts["pole"] = len(a) + len(b) + np.arange(len(pole))
    return points, labels, parts


def seeds_in(n, index, count):
    dynamic = np.zeros(n, bool)
    dynamic[index[:count]] = True
    return dynamic


def test_a_seeded_cluster_is_flagged_whole_and_nothing_else():
    points, labels, parts = scene()
    dynamic = seeds_in(len(points), parts["a"][100:], 3)
    out = spread_over_clusters(points, labels, dynamic, MOVABLE, link_m=0.4, min_seeds=3)
    assert out[parts["a"]].all()  # the car, its parts called pole included
    assert not out[parts["b"]].any()
    assert not out[parts["pole"]].any()


def test_fewer_seeds_than_asked_flag_nothing_more():
    points, labels, parts = scene()
    dynamic = seeds_in(len(points), parts["a"][100:], 2)
    out = spread_over_clusters(points, labels, dynamic, MOVABLE, link_m=0.4, min_seeds=3)
    assert np.array_equal(out, dynamic)


def test_a_static_class_is_never_a_seed():
    points, labels, parts = scene()
    dynamic = seeds_in(len(points), parts["pole"], 5)
    out = spread_over_clusters(points, labels, dynamic, MOVABLE, link_m=0.4, min_seeds=1)
    assert np.array_equal(out, dynamic)


def test_two_cars_closer_than_a_cell_are_one_cluster():
    """Car B moved to 0.3 m behind car A: their cells touch, so seeds on A flag B too (why
    cluster_link_m stays short)."""
    points, labels, parts = scene()
    points[parts["b"], 0] -= 5.0 - 2.3  # B from x = 5 to x = 2.3, 0.3 m behind A's end
    dynamic = seeds_in(len(points), parts["a"][100:], 3)
    out = spread_over_clusters(points, labels, dynamic, MOVABLE, link_m=0.4, min_seeds=3)
    assert out[parts["a"]].all() and out[parts["b"]].all()
    assert not out[parts["pole"]].any()


@pytest.mark.parametrize("count", [12, 40])
def test_a_cluster_with_few_of_its_points_flagged_is_not_dynamic(count):
    """Car A (2,000 points) with `count` flagged: enough seeds, but under a tenth of the car
    (a parked car that rays grazed where a mover passed close by); 200 make it dynamic."""
    points, labels, parts = scene()
    n_a = len(parts["a"])
    dynamic = seeds_in(len(points), parts["a"][100:], count)
    out = spread_over_clusters(
        points, labels, dynamic, MOVABLE, link_m=0.4, min_seeds=10, min_fraction=0.1
    )
    assert np.array_equal(out, dynamic)
    assert count < 0.1 * n_a
    # flags on a tenth of the car make it dynamic
    many = seeds_in(len(points), parts["a"][100:], int(np.ceil(0.1 * n_a)))
    out = spread_over_clusters(
        points, labels, many, MOVABLE, link_m=0.4, min_seeds=10, min_fraction=0.1
    )
    assert out[parts["a"]].all() and not out[parts["b"]].any()
