"""A ROS 2 bag the way `ros2 bag record -s mcap` writes it: a folder with `metadata.yaml` and
one MCAP file `<folder name>_0.mcap`.

    with Rosbag2Writer("out/drive", ros_distro="humble") as bag:
        bag.write_transforms([("base_link", "velodyne", t, T)], t, static=True)
        bag.write_cloud("/velodyne_points", points, "velodyne", t, t)

What `ros2 bag play` and the readers need, as rosbag2 writes it: every Channel record carries
its `offered_qos_profiles` (the QoS the player publishes with: `/tf_static`, and the map,
transient_local so that late subscribers such as tf2's static listener and RViz get them);
the MCAP file has the `rosbag2` metadata record naming the ROS distro; `metadata.yaml` is
version 5 (Humble's, which Iron and Jazzy read too) with per-topic counts and QoS. All times
are integer nanoseconds.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from tisem.io.mcap_writer import Ros2McapWriter

METADATA_VERSION = 5
# rmw enums as rosbag2 (Humble) stores them: history KEEP_LAST=1, reliability RELIABLE=1,
# durability TRANSIENT_LOCAL=1 / VOLATILE=2, liveliness AUTOMATIC=1
_INFINITE = {"sec": 9223372036, "nsec": 854775807}  # rmw's "no limit" duration


def qos_profile(*, transient_local: bool = False, depth: int = 10) -> dict:
    """One offered QoS profile (reliable; transient_local or volatile), as rosbag2 stores it."""
    return {
        "history": 1,
        "depth": depth,
        "reliability": 1,
        "durability": 1 if transient_local else 2,
        "deadline": dict(_INFINITE),
        "lifespan": dict(_INFINITE),
        "liveliness": 1,
        "liveliness_lease_duration": dict(_INFINITE),
        "avoid_ros_namespace_conventions": False,
    }


def qos_yaml(profiles: list[dict]) -> str:
    """The `offered_qos_profiles` text of a channel and of metadata.yaml (a YAML list)."""
    return yaml.safe_dump(profiles, default_flow_style=False, sort_keys=False).strip()


# latched topics: tf2's static broadcaster offers transient_local with depth 1
TRANSIENT_LOCAL_TOPICS = ("/tf_static",)


class Rosbag2Writer(Ros2McapWriter):
    """`Ros2McapWriter` into a rosbag2 folder; `finish()` writes metadata.yaml.

    `latched`: topics besides /tf_static offered transient_local (e.g. a map published once).
    A folder that holds a bag already is refused (as rosbag2 does), or with `overwrite` its
    metadata.yaml and .mcap files are replaced.
    """

    def __init__(
        self,
        folder: str | Path,
        *,
        ros_distro: str = "humble",
        compression: str = "zstd",
        latched: tuple[str, ...] = (),
        overwrite: bool = False,
    ) -> None:
        self.folder = Path(folder)
        if (self.folder / "metadata.yaml").exists():
            if not overwrite:
                raise FileExistsError(f"{self.folder} already holds a bag (metadata.yaml)")
            for old in [self.folder / "metadata.yaml", *self.folder.glob("*.mcap")]:
                old.unlink()
        self.folder.mkdir(parents=True, exist_ok=True)
        self.file = self.folder / f"{self.folder.name}_0.mcap"
        super().__init__(self.file, compression=compression)
        self.latched = set(TRANSIENT_LOCAL_TOPICS) | set(latched)
        self.ros_distro = ros_distro
        self._writer.add_metadata("rosbag2", {"ROS_DISTRO": ros_distro})
        self._topics: dict[str, dict] = {}  # topic -> type, qos text, count
        self._first_ns: int | None = None
        self._last_ns: int | None = None

    def write(
        self,
        topic: str,
        type_name: str,
        message: dict,
        log_time_ns: int,
        publish_time_ns: int | None = None,
        sequence: int = 0,
    ) -> None:
        if topic not in self._topics:
            latched = topic in self.latched
            qos = qos_yaml([qos_profile(transient_local=latched, depth=1 if latched else 10)])
            self.channel_metadata[topic] = {"offered_qos_profiles": qos}
            self._topics[topic] = {"type": type_name, "qos": qos, "count": 0}
        elif self._topics[topic]["type"] != type_name:
            raise ValueError(
                f"topic {topic} carries {self._topics[topic]['type']}, not {type_name}"
            )
        super().write(topic, type_name, message, log_time_ns, publish_time_ns, sequence)
        self._topics[topic]["count"] += 1
        t = int(log_time_ns)
        self._first_ns = t if self._first_ns is None else min(self._first_ns, t)
        self._last_ns = t if self._last_ns is None else max(self._last_ns, t)

    def metadata(self) -> dict:
        """metadata.yaml's content for what was written so far."""
        start = self._first_ns or 0
        duration = (self._last_ns - start) if self._last_ns is not None else 0
        count = sum(t["count"] for t in self._topics.values())
        topics = [
            {
                "topic_metadata": {
                    "name": name,
                    "type": t["type"],
                    "serialization_format": "cdr",
                    "offered_qos_profiles": t["qos"],
                },
                "message_count": t["count"],
            }
            for name, t in self._topics.items()
        ]
        return {
            "rosbag2_bagfile_information": {
                "version": METADATA_VERSION,
                "storage_identifier": "mcap",
                "duration": {"nanoseconds": duration},
                "starting_time": {"nanoseconds_since_epoch": start},
                "message_count": count,
                "topics_with_message_count": topics,
                "compression_format": "",
                "compression_mode": "",
                "relative_file_paths": [self.file.name],
                "files": [
                    {
                        "path": self.file.name,
                        "starting_time": {"nanoseconds_since_epoch": start},
                        "duration": {"nanoseconds": duration},
                        "message_count": count,
                    }
                ],
            }
        }

    def finish(self) -> None:
        if self._file is None:
            return
        super().finish()
        (self.folder / "metadata.yaml").write_text(
            yaml.safe_dump(self.metadata(), default_flow_style=False, sort_keys=False)
        )
