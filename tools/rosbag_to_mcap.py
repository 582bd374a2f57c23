#!/usr/bin/env python
"""Convert a ROS 1 bag or a ROS 2 bag folder (.db3 or .mcap storage) into this project's MCAP layout.

    python tools/rosbag_to_mcap.py drive.bag drive.mcap --image-format jpeg
    python tools/rosbag_to_mcap.py drive_bag/ drive.mcap --camera-topic /zed/left/image_rect_color

Topics are found and associated as `ssmvpr-slam run` finds them (by type, or named here); the
frames are written to /camera/image_raw (or .../compressed), /camera_rear/..., /lidar/points,
/odom and /ground_truth. `run` reads the bag directly too; this gives a single file to share.
"""

from __future__ import annotations

import argparse
import sys

from _mcap_conversion import convert_to_mcap

from frontend.config import McapSourceConfig
from frontend.sources import RosbagSource

TOPICS = ("camera_topic", "rear_camera_topic", "lidar_topic", "odom_topic", "gt_topic")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", help="a ROS 1 .bag file or a ROS 2 bag folder")
    parser.add_argument("output", help="MCAP file to write")
    for field in TOPICS:
        flag = "--" + field.replace("_", "-")
        parser.add_argument(flag, dest=field, help=f"{field.replace('_', ' ')} (default: found by type; '' = off)")
    parser.add_argument("--image-format", default="raw", choices=["raw", "jpeg", "png"])
    parser.add_argument("--max-frames", type=int, default=None, help="stop after N frames")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    topics = {field: getattr(args, field) for field in TOPICS if getattr(args, field) is not None}
    return convert_to_mcap(
        lambda: RosbagSource(args.bag, McapSourceConfig(**topics)),
        args.output,
        max_frames=args.max_frames,
        image_format=args.image_format,
    )


if __name__ == "__main__":
    sys.exit(main())
