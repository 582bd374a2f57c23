#!/usr/bin/env python
"""Convert a KITTI odometry sequence folder into a ROS 2 MCAP log (Foxglove-ready).

    python tools/kitti_to_mcap.py dataset/sequences/00 seq00.mcap --image-format jpeg

Images go to /camera/image_raw (or .../compressed), scans to /lidar/points, ground truth
to /ground_truth (PoseStamped). Read it back with ``frontend.sources.open_source``.
"""

from __future__ import annotations

import argparse
import sys

from _mcap_conversion import convert_to_mcap

from frontend.config import KittiSourceConfig
from frontend.sources import KittiSource


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", help="KITTI sequence folder (sequences/XX)")
    parser.add_argument("output", help="MCAP file to write")
    parser.add_argument("--poses", help="ground-truth poses file (default: poses/XX.txt)")
    parser.add_argument("--camera", default="auto", choices=["auto", "image_2", "image_0", "none"])
    parser.add_argument("--no-points", action="store_true", help="leave the LiDAR scans out")
    parser.add_argument("--gt-frame", default="auto", choices=["auto", "lidar", "camera"])
    parser.add_argument("--image-format", default="raw", choices=["raw", "jpeg", "png"])
    parser.add_argument("--max-frames", type=int, default=None, help="stop after N frames")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    config = {
        "camera": args.camera,
        "load_points": not args.no_points,
        "poses_file": args.poses,
        "gt_frame": args.gt_frame,
    }
    return convert_to_mcap(
        lambda: KittiSource(args.sequence, KittiSourceConfig(**config)),
        args.output,
        max_frames=args.max_frames,
        image_format=args.image_format,
    )


if __name__ == "__main__":
    sys.exit(main())
