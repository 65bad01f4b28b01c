"""kitti_to_mcap.py --format rosbag2 (tisem.io.kitti_mcap, tisem.io.rosbag_writer): `rosbags`
reads the output as a rosbag2 bag with the QoS rosbag2 records (transient_local /tf_static),
the MCAP file names the ROS distro, and header stamps are start time + times.txt to the
nanosecond (real epoch stamps survive: no float seconds in between)."""

from __future__ import annotations

import numpy as np
import pytest
from mcap.reader import make_reader

pytest.importorskip("rosbags", reason="the rosbags package (tisem[mcap]) is not installed")

from rosbags.interfaces import QosDurability, QosReliability  # noqa: E402
from rosbags.rosbag2 import Reader  # noqa: E402
from rosbags.rosbag2.metadata import parse_qos  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from test_mcap_kitti import load_app, write_tiny_sequence  # noqa: E402

from tisem.io.stamps import decimal_seconds_to_ns, parse_start_time_ns  # noqa: E402

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
# added to an epoch start, these are not float seconds to the nanosecond (a float has ~240 ns
# steps there): only integer nanoseconds end to end give the stamps below
TIMES = ["0.000000e+00", "1.036712e-01", "2.073424e-01", "3.110136e-01"]
START = "1700000000.123456789"


def test_start_times_and_times_txt_are_exact_nanoseconds():
    assert parse_start_time_ns(START) == 1_700_000_000_123_456_789
    assert parse_start_time_ns("1700000000123456789") == 1_700_000_000_123_456_789
    assert parse_start_time_ns("1700000000") == 1_700_000_000_000_000_000
    assert parse_start_time_ns("0") == 0
    assert decimal_seconds_to_ns("1.036712e-01") == 103_671_200
    for bad in ("-1", "nan", "soon", "1e300"):
        with pytest.raises(ValueError):
            parse_start_time_ns(bad)


def test_kitti_to_mcap_writes_a_rosbag2_bag_with_qos_and_exact_stamps(tmp_path, capsys):
    seq = write_tiny_sequence(tmp_path / "seq", n_scans=4, n_points=200)
    (seq / "times.txt").write_text("\n".join(TIMES) + "\n")
    app = load_app("kitti_to_mcap")
    out = tmp_path / "drive"
    assert (
        app.main(
            [
                str(seq),
                str(out),
                "--format",
                "rosbag2",
                "--start-time",
                START,
                "--ros-distro",
                "jazzy",
            ]
        )
        == 0
    )
    assert "4 scans" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["drive_0.mcap", "metadata.yaml"]

    start_ns = 1_700_000_000_123_456_789
    expected = [start_ns + decimal_seconds_to_ns(t) for t in TIMES]
    stamps: dict[str, list[int]] = {}
    with Reader(out) as reader:
        assert reader.message_count == 1 + 4 + 4
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
        assert set(qos) == {"/tf_static", "/tf", "/velodyne_points"}
        assert all(len(profiles) == 1 for profiles in qos.values())
        assert qos["/tf_static"][0].durability == QosDurability.TRANSIENT_LOCAL
        assert qos["/tf"][0].durability == QosDurability.VOLATILE
        assert all(p[0].reliability == QosReliability.RELIABLE for p in qos.values())
        for conn, _, data in reader.messages():
            msg = HUMBLE.deserialize_cdr(data, conn.msgtype)
            headers = (
                [t.header for t in msg.transforms] if conn.topic.startswith("/tf") else [msg.header]
            )
            stamps.setdefault(conn.topic, []).extend(
                h.stamp.sec * 10**9 + h.stamp.nanosec for h in headers
            )
    assert stamps["/velodyne_points"] == expected == stamps["/tf"]
    assert stamps["/tf_static"] == expected[:1]

    with open(out / "drive_0.mcap", "rb") as f:
        mcap = make_reader(f)
        metadata = {m.name: m.metadata for m in mcap.iter_metadata()}
        channels = mcap.get_summary().channels.values()
    assert metadata["rosbag2"] == {"ROS_DISTRO": "jazzy"}
    for channel in channels:  # what `ros2 bag play` reads from the storage itself
        (profile,) = parse_qos(channel.metadata["offered_qos_profiles"])
        assert profile == qos[channel.topic][0]


def test_a_folder_with_a_bag_is_not_overwritten(tmp_path):
    seq = write_tiny_sequence(tmp_path / "seq", n_scans=2, n_points=100)
    app = load_app("kitti_to_mcap")
    assert app.main([str(seq), str(tmp_path / "bag"), "--format", "rosbag2"]) == 0
    before = (tmp_path / "bag" / "metadata.yaml").read_bytes()
    assert app.main([str(seq), str(tmp_path / "bag"), "--format", "rosbag2"]) == 2
    assert app.main([str(seq), str(tmp_path / "x"), "--start-time", "yesterday"]) == 2
    assert (tmp_path / "bag" / "metadata.yaml").read_bytes() == before
    assert not np.any([p.name == "x" for p in tmp_path.iterdir()])
