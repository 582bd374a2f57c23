#!/usr/bin/env python
"""Convert an image folder (+ optional TUM/KITTI poses) into a ROS 2 MCAP log.

    python tools/folder_to_mcap.py my_traverse/ traverse.mcap --poses poses.txt --pose-role both

Images go to /camera/image_raw (or .../compressed); poses to /ground_truth (PoseStamped)
and/or /odom (Odometry) by ``--pose-role``. Read it back with ``frontend.sources.open_source``.
"""

from __future__ import annotations

import argparse
import sys

from _mcap_conversion import convert_to_mcap

from frontend.config import FolderSourceConfig
from frontend.sources import FolderSource


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", help="folder with images (or images/, rgb/, ...)")
    parser.add_argument("output", help="MCAP file to write")
    parser.add_argument("--image-dir", help="image sub-folder (default: detected)")
    parser.add_argument("--poses", help="TUM or KITTI poses file (default: detected)")
    parser.add_argument("--times", help="one timestamp per image (default: times.txt)")
    parser.add_argument("--pose-role", default="gt", choices=["gt", "logged", "both"])
    parser.add_argument("--frame-period", type=float, default=None, help="s, when no times")
    parser.add_argument("--image-format", default="raw", choices=["raw", "jpeg", "png"])
    parser.add_argument("--max-frames", type=int, default=None, help="stop after N frames")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    options = {"image_dir": args.image_dir, "poses_file": args.poses, "times_file": args.times}
    options["pose_role"] = args.pose_role
    if args.frame_period is not None:
        options["frame_period_s"] = args.frame_period
    return convert_to_mcap(
        lambda: FolderSource(args.folder, FolderSourceConfig(**options)),
        args.output,
        max_frames=args.max_frames,
        image_format=args.image_format,
    )


if __name__ == "__main__":
    sys.exit(main())
