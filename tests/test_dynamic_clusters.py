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


def test_every_point_in_a_flagged_cell_is_flagged_on_its_faces_too():
    """Road points on the faces of car A's cells, and just outside them on every side: exactly
    those whose cell (floor(p / link)) holds a point of A are flagged."""
    points, labels, parts = scene()
    link = 0.4
    a_cells = {tuple(c) for c in np.floor(points[parts["a"]] / link).astype(int).tolist()}
    rng = np.random.default_rng(0)
    probes = np.floor(rng.uniform(-4.0, 4.0, (400, 3)) / link) * link  # cell corners
    probes[::2, rng.integers(0, 3)] += link - 1e-4  # just inside the upper face
    probes[1::4] += rng.uniform(0, link, (100, 3))
    all_points = np.concatenate([points, probes])
    all_labels = np.r_[labels, np.full(len(probes), ROAD)]
    dynamic = seeds_in(len(all_points), parts["a"][100:], 3)
    out = spread_over_clusters(all_points, all_labels, dynamic, MOVABLE, link, min_seeds=3)
    cells = np.floor(probes / link).astype(int).tolist()
    want = np.array([tuple(c) in a_cells for c in cells])
    assert want.any() and not want.all()
    assert np.array_equal(out[len(points) :], want)


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


PERSON, TRUNK = 6, 16
THIN_STATIC = np.zeros(20, bool)
THIN_STATIC[[16, 18, 19]] = True  # trunk, pole, traffic-sign


def walker(x=0.0):
    """A walker (a 0.5 x 0.5 x 1.8 m box) whose top 0.8 m the network calls trunk, a patch
    with cells of its own (link 0.4 m), and a pole 3 m away."""
    body = box_points((x, 0, 0), (x + 0.5, 0.5, 1.8))
    pole = box_points((x + 3.0, 0, 0), (x + 3.2, 0.2, 2))
    points = np.concatenate([body, pole])
    labels = np.r_[np.where(body[:, 2] > 1.0, TRUNK, PERSON), np.full(len(pole), POLE)]
    return points, labels, np.arange(len(body)), len(body) + np.arange(len(pole))


def test_thin_classes_join_the_cluster_of_a_walker_they_touch():
    points, labels, body, pole = walker()
    person = body[labels[body] == PERSON]
    dynamic = seeds_in(len(points), person, 40)  # of 250
    args = dict(link_m=0.4, min_seeds=10, min_fraction=0.1)
    alone = spread_over_clusters(points, labels, dynamic, MOVABLE, **args)
    assert alone[person].all()
    assert not alone[body[labels[body] == TRUNK]].all()  # the top's own cells stay
    joined = spread_over_clusters(points, labels, dynamic, MOVABLE, joining=THIN_STATIC, **args)
    assert joined[body].all()
    assert not joined[pole].any()


def test_joining_points_count_for_neither_test():
    """Flags on the walker's trunk-called top make no cluster (a pole a stray ray flags is
    none); the fraction is of the movable-class points: 10 % of the person part flags the
    walker though the top doubles its points."""
    points, labels, body, pole = walker()
    person = body[labels[body] == PERSON]
    top = body[labels[body] == TRUNK]
    args = dict(link_m=0.4, min_seeds=1, min_fraction=0.1, joining=THIN_STATIC)
    for flagged in (top, pole):
        dynamic = seeds_in(len(points), flagged, len(flagged))
        out = spread_over_clusters(points, labels, dynamic, MOVABLE, **args)
        assert np.array_equal(out, dynamic)
    assert len(top) > 0.5 * len(person)
    tenth = int(np.ceil(0.1 * len(person)))
    out = spread_over_clusters(
        points, labels, seeds_in(len(points), person, tenth), MOVABLE, **args
    )
    assert out[body].all() and not out[pole].any()
