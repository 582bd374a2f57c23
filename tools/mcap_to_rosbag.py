#!/usr/bin/env python
"""Convert a ROS 2 MCAP log (e.g. from `ssmvpr-slam simulate`) into a ROS 1 bag or a ROS 2 bag.

    python tools/mcap_to_rosbag.py demo.mcap demo.bag --format ros1
    python tools/mcap_to_rosbag.py demo.mcap demo_bag --format ros2-sqlite3   # or ros2-mcap

`ssmvpr-slam run` reads all three as it reads the MCAP (same topics, same frames).
"""

from __future__ import annotations

import argparse
import sys
from typing import get_args

from frontend.errors import FrontendInputError
from frontend.sources.rosbag_convert import BagFormat, mcap_to_rosbag


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", help="MCAP log of ROS 2 messages")
    parser.add_argument("output", help="the bag: a .bag file (ros1) or a folder (ros2-*), not existing yet")
    parser.add_argument("--format", default="ros1", choices=get_args(BagFormat))
    args = parser.parse_args(argv)
    try:
        out = mcap_to_rosbag(args.log, args.output, args.format)
    except (FrontendInputError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
