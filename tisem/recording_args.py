"""The command-line options that say how a recording is read, for every command that reads one.

`tisem map-mcap` reads one recording; `tisem fleet` and `tisem batch` read many, each with the
same options (a fleet's robots record alike). One definition of the options, so a bag that
needs `--gt-field gt_label --static-tf "..."` to be read by one command is read the same way by
the others.
"""

from __future__ import annotations

import argparse

from tisem import cli
from tisem.labels import LABEL_SPACES


def add_recording_args(p: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """The "recording" argument group (returned, for a command's own options of its input)."""
    g = p.add_argument_group("recording (MCAP, rosbag2, ROS 1 bag)")
    g.add_argument("--topic", help="point-cloud topic (needed only when there are several)")
    g.add_argument("--label-field", default="label", help="per-point label field (default label)")
    g.add_argument(
        "--label-space",
        choices=LABEL_SPACES,
        default="auto",
        help="label values are raw SemanticKITTI ids, train ids 0..19, or either (auto, the "
        "default: train ids in a scan whose values all are, and some are no raw id)",
    )
    g.add_argument(
        "--prob-field",
        help="a count=C float field of class probabilities (instead of --label-field)",
    )
    g.add_argument("--gt-field", help="ground-truth label field (same label space): score the map")
    g.add_argument("--map-frame", default="map", help="the fixed frame of the map (default map)")
    g.add_argument("--pose-topic", help="Odometry / PoseStamped topic instead of /tf")
    g.add_argument(
        "--pose-child-frame",
        help="the frame a PoseStamped is the pose of (default: "
        "the top of the cloud frame's /tf_static chain, "
        "e.g. base_link, or the cloud frame itself)",
    )
    g.add_argument(
        "--tf-tolerance-ms",
        type=float,
        default=0.0,
        help="accept a stamp this far outside a transform's samples (default 0)",
    )
    g.add_argument(
        "--static-tf",
        action="append",
        metavar='"X Y Z QX QY QZ QW PARENT CHILD"',
        help="a static transform the recording lacks or gets wrong, e.g. the sensor mount "
        "base_link -> velodyne, in quotes (metres, then the quaternion, in the order of "
        "tf2_ros static_transform_publisher): it replaces the recording's transforms of "
        "CHILD; repeatable",
    )
    return g


def recording_options(args: argparse.Namespace, **frames):
    """`McapOptions` of the recording options in `args`, checked (ValueError naming the
    option); `frames`: first, last and num_classes where the command sets them."""
    from tisem.io.mcap_options import McapOptions

    options = McapOptions(
        topic=args.topic,
        label_field=args.label_field,
        label_space=args.label_space,
        prob_field=args.prob_field,
        gt_field=args.gt_field,
        map_frame=args.map_frame,
        pose_topic=args.pose_topic,
        pose_child_frame=args.pose_child_frame,
        tf_tolerance_s=cli.finite_number("--tf-tolerance-ms", args.tf_tolerance_ms) / 1e3,
        static_tf=static_tf_option(args.static_tf),
        **frames,
    )
    options.validate()
    return options


def static_tf_option(given: list[str] | None) -> tuple:
    """Each --static-tf "X Y Z QX QY QZ QW PARENT CHILD" as an item of `McapOptions.static_tf`.
    One quoted argument, not nine: argparse takes a number such as -8e-05 for an option."""
    out = []
    for text in given or ():
        values = text.split()
        try:
            if len(values) != 9:
                raise ValueError
            *numbers, parent, child = values
            out.append((parent, child, *(float(v) for v in numbers)))
        except ValueError:
            raise ValueError(
                f"--static-tf {text!r}: expected X Y Z QX QY QZ QW (numbers), then PARENT CHILD"
            ) from None
    return tuple(out)
