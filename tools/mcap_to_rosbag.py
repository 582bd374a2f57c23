#!/usr/bin/env python
"""Convert a ROS 2 MCAP log (e.g. from `ssmvpr-slam simulate`) into a ROS 1 bag or a ROS 2 bag.

    python tools/mcap_to_rosbag.py demo.mcap demo.bag --format ros1
    python tools/mcap_to_rosbag.py demo.mcap demo_bag --format ros2-sqlite3   # or ros2-mcap

`ssmvpr-slam run` reads all three as it reads the MCAP (same topics, same frames); the tests
that check so import `mcap_to_rosbag` from here. ROS 2 bags take the CDR bytes as they are; ROS 1
bags get each message re-serialised with ROS 1's definitions (a Header gains its `seq`).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal, get_args

from mcap.reader import make_reader
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

from frontend.errors import FrontendInputError

BagFormat = Literal["ros1", "ros2-sqlite3", "ros2-mcap"]
ROS2 = get_typestore(Stores.ROS2_HUMBLE)
ROS1 = get_typestore(Stores.ROS1_NOETIC)


def _messages(log: Path) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, message type, log time ns, CDR bytes) of every message, in log-time order."""
    with open(log, "rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages(log_time_order=True):
            if schema is None or channel.message_encoding != "cdr":
                raise FrontendInputError(f"{log}: {channel.topic} is not a ROS 2 (CDR) message stream")
            yield channel.topic, schema.name, message.log_time, message.data


def _as_ros1(message: Any, msgtype: str) -> Any:
    """The ROS 1 message with the same field values (fields ROS 2 lacks, a Header's seq, are 0;
    CameraInfo's ``K`` and the like are ROS 2's lower-case ``k``)."""
    cls: Any = ROS1.types[msgtype]
    values = {}
    for field in dataclasses.fields(cls):
        if field.name == "__msgtype__":
            continue
        value = getattr(message, field.name, getattr(message, field.name.lower(), 0))
        if hasattr(value, "__msgtype__"):
            value = _as_ros1(value, value.__msgtype__)
        elif isinstance(value, list) and value and hasattr(value[0], "__msgtype__"):
            value = [_as_ros1(v, v.__msgtype__) for v in value]
        values[field.name] = value
    return cls(**values)


def mcap_to_rosbag(log: str | Path, out: str | Path, bag_format: BagFormat) -> Path:
    """Write `log` as a bag at `out` (a .bag file for ros1, a bag folder for ros2); returns `out`."""
    log, out = Path(log), Path(out)
    if out.exists():
        raise FrontendInputError(f"{out}: already exists")
    if bag_format == "ros1":
        with Ros1Writer(out) as writer:
            connections: dict[str, Any] = {}
            for topic, msgtype, time, data in _messages(log):
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=ROS1)
                message = _as_ros1(ROS2.deserialize_cdr(data, msgtype), msgtype)
                writer.write(connections[topic], time, ROS1.serialize_ros1(message, msgtype))
        return out
    storage = StoragePlugin.SQLITE3 if bag_format == "ros2-sqlite3" else StoragePlugin.MCAP
    with Ros2Writer(out, version=9, storage_plugin=storage) as writer2:
        connections = {}
        for topic, msgtype, time, data in _messages(log):
            if topic not in connections:
                connections[topic] = writer2.add_connection(topic, msgtype, typestore=ROS2)
            writer2.write(connections[topic], time, data)
    return out


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
