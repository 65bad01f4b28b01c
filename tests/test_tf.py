"""TfBuffer against analytic poses: chains, interpolation, static edges, errors."""

from __future__ import annotations

import numpy as np
import pytest

from tisem.io.tf import (
    ConnectivityError,
    ExtrapolationError,
    TfBuffer,
    invert,
    make_transform,
    matrix_to_quat,
    quat_to_matrix,
    slerp,
)

NS = 1_000_000_000


def yaw(angle: float) -> np.ndarray:
    return np.array([0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)])


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def T_of(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


# the analytic motion: constant velocity and a constant yaw rate, sampled at 20 Hz
V = np.array([3.0, -1.0, 0.2])
W = 0.7  # rad/s
T_BASE_LIDAR = T_of(rot_z(0.3) @ quat_to_matrix([0.1, 0.0, 0.0, 1.0]), [0.5, 0.1, 1.6])
T_MAP_ODOM = T_of(rot_z(-0.2), [10.0, 5.0, 0.0])


def odom_base(t_s: float) -> np.ndarray:
    return T_of(rot_z(W * t_s), V * t_s + [1.0, 2.0, 0.0])


@pytest.fixture
def chain() -> TfBuffer:
    """map -> odom (static) -> base_link (20 Hz, 0..2 s) -> lidar (static)."""
    tf = TfBuffer()
    tf.add("map", "odom", 0, T_MAP_ODOM[:3, 3], matrix_to_quat(T_MAP_ODOM[:3, :3]), static=True)
    tf.add(
        "/base_link",
        "lidar",
        0,
        T_BASE_LIDAR[:3, 3],
        matrix_to_quat(T_BASE_LIDAR[:3, :3]),
        static=True,
    )  # ROS 1 style leading '/' is stripped
    for k in range(41):
        t = k * NS // 20
        tf.add("odom", "base_link", t, odom_base(t / NS)[:3, 3], yaw(W * t / NS))
    return tf


def test_lookups_between_samples_match_the_analytic_chain(chain):
    rng = np.random.default_rng(1)
    stamps = np.sort(rng.integers(0, 2 * NS, 200))
    got = chain.lookup_many("map", "lidar", stamps)
    for T, t in zip(got, stamps):
        expect = T_MAP_ODOM @ odom_base(t / NS) @ T_BASE_LIDAR
        assert np.abs(T - expect).max() < 1e-9, f"stamp {t}"


def test_inverse_and_sibling_lookups(chain):
    t = 1_234_567_890
    T = chain.lookup("map", "lidar", t)
    assert np.abs(chain.lookup("lidar", "map", t) - invert(T)).max() < 1e-12
    # odom and lidar share base_link's branch: odom -> lidar equals odom->base @ base->lidar
    expect = odom_base(t / NS) @ T_BASE_LIDAR
    assert np.abs(chain.lookup("odom", "lidar", t) - expect).max() < 1e-9
    assert np.abs(chain.lookup("lidar", "lidar", t) - np.eye(4)).max() == 0


def test_exact_sample_stamps_and_ends(chain):
    for t in (0, NS // 20, 2 * NS):
        expect = T_MAP_ODOM @ odom_base(t / NS) @ T_BASE_LIDAR
        assert np.abs(chain.lookup("map", "lidar", t) - expect).max() < 1e-12


def test_extrapolation_is_an_error_that_names_the_edge_and_times(chain):
    with pytest.raises(ExtrapolationError, match=r"odom -> base_link.*after its last"):
        chain.lookup("map", "lidar", 2 * NS + 1_000_000)
    with pytest.raises(ExtrapolationError, match="before its first"):
        chain.lookup("map", "lidar", -1)


def test_tolerance_clamps_to_the_nearest_sample(chain):
    chain.max_extrapolation_ns = 5_000_000
    T = chain.lookup("map", "lidar", 2 * NS + 4_000_000)
    assert np.abs(T - T_MAP_ODOM @ odom_base(2.0) @ T_BASE_LIDAR).max() < 1e-12
    with pytest.raises(ExtrapolationError):
        chain.lookup("map", "lidar", 2 * NS + 6_000_000)


def test_static_edges_hold_at_any_time_and_the_latest_wins(chain):
    assert np.allclose(chain.lookup("base_link", "lidar", 10**15), T_BASE_LIDAR)
    chain.add("base_link", "lidar", 5, [0, 0, 2.0], [0, 0, 0, 1], static=True)
    assert np.allclose(chain.lookup("base_link", "lidar", 0)[:3, 3], [0, 0, 2])


def test_unconnected_and_unknown_frames(chain):
    chain.add("world", "gps", 0, [0, 0, 0], [0, 0, 0, 1], static=True)
    with pytest.raises(ConnectivityError, match="not connected"):
        chain.lookup("map", "gps", 0)
    with pytest.raises(ConnectivityError, match="known frames"):
        chain.lookup("map", "camera", 0)
    assert not chain.can_connect("map", "gps") and chain.can_connect("map", "lidar")


def test_a_second_parent_is_ignored_and_reported(chain):
    chain.add("map", "base_link", 0, [0, 0, 0], [0, 0, 0, 1])
    assert any("base_link" in w and "parent" in w for w in chain.warnings)
    assert (
        np.abs(chain.lookup("map", "lidar", 0) - T_MAP_ODOM @ odom_base(0) @ T_BASE_LIDAR).max()
        < 1e-12
    )


def test_single_sample_edge_only_at_its_stamp():
    tf = TfBuffer()
    tf.add("map", "a", 100, [1, 0, 0], [0, 0, 0, 1])
    assert tf.lookup("map", "a", 100)[0, 3] == 1
    with pytest.raises(ExtrapolationError):
        tf.lookup("map", "a", 101)
    assert tf.promote_constant_edges() == ["a"]
    assert tf.lookup("map", "a", 10**12)[0, 3] == 1


def test_duplicate_stamps_keep_the_latest_and_unsorted_input_is_sorted():
    tf = TfBuffer()
    for t, x in ((20, 2.0), (0, 0.0), (10, 5.0), (10, 1.0)):
        tf.add("map", "a", t, [x, 0, 0], [0, 0, 0, 1])
    assert tf.lookup("map", "a", 5)[0, 3] == pytest.approx(0.5)
    assert tf.lookup("map", "a", 15)[0, 3] == pytest.approx(1.5)


def test_slerp_takes_the_short_way_and_handles_sign_flips():
    q0, q1 = yaw(0.1), -yaw(0.5)  # same rotation as yaw(0.5), opposite sign
    q = slerp(q0[None], q1[None], np.array([0.5]))[0]
    assert np.allclose(quat_to_matrix(q), rot_z(0.3), atol=1e-12)
    same = slerp(q0[None], q0[None], np.array([0.3]))[0]
    assert np.allclose(same, q0)


@pytest.mark.parametrize("seed", range(5))
def test_matrix_quaternion_round_trip(seed):
    rng = np.random.default_rng(seed)
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    R = quat_to_matrix(q)
    back = matrix_to_quat(R)
    assert np.allclose(quat_to_matrix(back), R, atol=1e-12), f"seed {seed}"
    assert back[3] >= 0
    # 180 degree turns (trace -1) go through the other branches
    for axis in np.eye(3):
        R = make_transform([0, 0, 0], [*axis, 0.0])[:3, :3]
        assert np.allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-12)


def test_bad_transforms_are_ignored_with_a_warning():
    tf = TfBuffer()
    tf.add("map", "a", 0, [np.nan, 0, 0], [0, 0, 0, 1])
    tf.add("map", "b", 0, [0, 0, 0], [0, 0, 0, 0])
    tf.add("map", "map", 0, [0, 0, 0], [0, 0, 0, 1])
    tf.add("map", "c", 2**63, [0, 0, 0], [0, 0, 0, 1])
    assert len(tf.warnings) == 4 and tf.frames == set()


def test_a_quaternion_of_huge_components_is_normalised_without_overflow():
    """Damaged bytes can decode to finite but huge components, whose norm overflows float64."""
    tf = TfBuffer()
    with np.errstate(all="raise"):
        tf.add("map", "a", 0, [1, 2, 3], [0, 0, 1e300, 1e300])  # 90 degrees about z
        T = tf.lookup("map", "a", 0)
    assert np.allclose(T[:3, :3], rot_z(np.pi / 2), atol=1e-12) and np.allclose(T[:3, 3], [1, 2, 3])


def test_ignored_transforms_are_counted_and_named_when_a_frame_is_missing():
    """16 map -> base_link transforms with zero quaternions: the error says so, instead of
    only 'frame map does not appear in any transform'."""
    tf = TfBuffer()
    for k in range(16):
        tf.add("map", "base_link", k * NS, [0, 0, 0], [0, 0, 0, 0])
    tf.add("base_link", "lidar", 0, [0, 0, 1], [0, 0, 0, 1], static=True)
    assert tf.warnings == ["ignored 16 transform(s) map -> base_link with a zero quaternion"]
    with pytest.raises(
        ConnectivityError,
        match=r"frame 'map' does not appear in any transform; "
        r"known frames: base_link, lidar; ignored 16 transform\(s\) map -> "
        r"base_link with a zero quaternion",
    ):
        tf.lookup("map", "lidar", 0)


def test_an_interpolation_across_missing_samples_is_found(chain):
    """What a lost /tf message looks like: two samples farther apart than the others."""
    stamps = [int(k * NS / 20) for k in range(40) if k not in (10, 11, 12)]
    tf = TfBuffer()
    tf.add("odom", "base_link", 0, [0, 0, 0], [0, 0, 0, 1], static=True)
    for t in stamps:
        tf.add("map", "odom", t, [t / NS, 0, 0], [0, 0, 0, 1])
    assert tf.interpolation_gap("map", "base_link", int(0.3 * NS)) is None
    gap = tf.interpolation_gap("map", "base_link", int(0.55 * NS))
    assert gap == (
        "edge map -> odom has no samples from 0.450000 s to 0.650000 s around the "
        "stamp (its median spacing is 50.0 ms)"
    )
    assert tf.interpolation_gap("base_link", "map", int(0.61 * NS)) == gap  # either direction
    one = TfBuffer()  # (one sample left of the edge: every pose is that sample's)
    one.add("map", "base_link", int(0.2 * NS), [0, 0, 0], [0, 0, 0, 1])
    assert one.interpolation_gap("map", "base_link", int(0.2 * NS)) is None
    assert one.interpolation_gap("map", "base_link", int(0.25 * NS)) == (
        "edge map -> base_link has 1 sample(s) left, at 0.200000 s: how far apart its samples "
        "were is unknown"
    )
    one.add("map", "base_link", int(0.65 * NS), [0, 0, 0], [0, 0, 0, 1])  # (two: no spacing)
    assert one.interpolation_gap("map", "base_link", int(0.25 * NS)) == (
        "edge map -> base_link has 2 sample(s) left, at 0.200000 s and 0.650000 s: how far "
        "apart its samples were is unknown"
    )
    assert one.interpolation_gap("map", "base_link", int(0.65 * NS)) is None
    # a stamp that is a sample's own is that sample, the gap beside it notwithstanding
    assert tf.interpolation_gap("map", "base_link", stamps[9]) is None  # 0.45 s
    assert tf.interpolation_gap("map", "base_link", stamps[-1]) is None
    assert tf.interpolation_gap("map", "base_link", stamps[-1] + 1) == (
        "edge map -> odom has no samples after 1.950000 s, its last (its median spacing is 50.0 ms)"
    )
    assert tf.interpolation_gap("map", "base_link", -1) == (
        "edge map -> odom has no samples before 0.000000 s, its first (its median spacing "
        "is 50.0 ms)"
    )


def test_a_stamp_that_is_a_sample_s_own_gets_that_sample_bit_for_bit():
    """A scan stamped at a /tf sample has that sample's pose whatever samples lie beside it
    (a cut file or a lost chunk takes them): the pose of the whole edge at the stamp equals,
    bit for bit, that of an edge holding only the sample."""
    rng = np.random.default_rng(3)
    stamps = [int(k * NS / 10) for k in range(6)]
    samples = [(rng.normal(size=3) * 10, rng.normal(size=4)) for _ in stamps]
    whole = TfBuffer()
    for t, (trans, quat) in zip(stamps, samples):
        whole.add("map", "base_link", t, trans, quat)
    for t, (trans, quat) in zip(stamps, samples):
        alone = TfBuffer()
        alone.add("map", "base_link", t, trans, quat)
        assert np.array_equal(
            whole.lookup("map", "base_link", t), alone.lookup("map", "base_link", t)
        )
    between = whole.lookup("map", "base_link", stamps[2] + 1)  # (and between them, slerp)
    assert not np.array_equal(between, whole.lookup("map", "base_link", stamps[2]))
