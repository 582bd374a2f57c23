"""Stream Frames out of a ROS 2 MCAP log, never holding more than a bounded window.

Topics are found by message type (or named in the config); the camera stream drives the
frames (the LiDAR when there is no camera) and the other streams are matched by nearest
timestamp (:mod:`frontend.sources.association`). An indexed log is read in log-time order
through its chunk index, unless its message index shows a topic whose log time goes back in
file order (a clock jump): then in file order, so the jump is seen and not interleaved
(:mod:`frontend.sources.clock`); a log without a usable summary (still being written, or cut off)
is read linearly in file order, and a cut is reported after every frame before it.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.records import Channel, Message, MessageIndex, Schema
from mcap.stream_reader import StreamReader
from mcap.summary import Summary
from mcap_ros2.decoder import DecoderFactory

from frontend.config import McapSourceConfig, McapWriterConfig, PoseFileConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.sources import ros_convert
from frontend.sources.association import Associated, StreamAssociator
from frontend.sources.base import Source
from frontend.sources.clock import StreamClock
from frontend.sources.ros_msgdefs import (
    COMPRESSED_IMAGE,
    IMAGE,
    ODOMETRY,
    POINT_CLOUD2,
    POSE_STAMPED,
    normalise_type,
)
from ssmvpr_common.poses import pose_problem

log = logging.getLogger("frontend.sources.mcap")

POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
_POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED)
_CAMERA_ROLES = ("camera", "rear_camera")
# role -> (types accepted when the topic is named, types auto-detected, default topic names)
_WRITER = McapWriterConfig()
ROLES: dict[str, tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]] = {
    "camera": (
        (IMAGE, COMPRESSED_IMAGE),
        (IMAGE, COMPRESSED_IMAGE),
        (_WRITER.camera_topic, _WRITER.compressed_camera_topic),
    ),
    # a second camera is never guessed from its type: only the writer's rear names or a named topic
    "rear_camera": (
        (IMAGE, COMPRESSED_IMAGE),
        (IMAGE, COMPRESSED_IMAGE),
        (_WRITER.rear_camera_topic, _WRITER.compressed_rear_camera_topic),
    ),
    "lidar": ((POINT_CLOUD2,), (POINT_CLOUD2,), (_WRITER.lidar_topic,)),
    "logged_pose": (_POSE_TYPES, (ODOMETRY,), (_WRITER.odom_topic,)),
    "gt_pose": (_POSE_TYPES, (POSE_STAMPED,), (_WRITER.gt_topic,)),
}
ROLE_CONFIG_FIELD = {
    "camera": "camera_topic",
    "rear_camera": "rear_camera_topic",
    "lidar": "lidar_topic",
    "logged_pose": "odom_topic",
    "gt_pose": "gt_topic",
}


@dataclass
class _Topic:
    role: str
    name: str
    type: str


class McapSource(Source):
    """Frames from an MCAP log; see the module docstring for how streams are combined."""

    def __init__(
        self,
        path: str | Path,
        config: McapSourceConfig | None = None,
        pose_config: PoseFileConfig | None = None,
    ) -> None:
        super().__init__()
        self.path = Path(path)
        self.config = config or McapSourceConfig()
        self._rotation_tolerance = (pose_config or PoseFileConfig()).rotation_tolerance
        if not self.path.is_file():
            raise FrontendInputError(f"{self.path}: MCAP file not found")
        self._scan_stopped: str | None = None  # why a linear channel scan ended early (cut or corrupt log)
        self._indexed, channels, counts = self._discover()
        present = {c.topic: t for c, t in channels}
        self._roles = self._select_topics(present)
        self.driver = self._pick_driver()
        self._length = counts.get(self._roles[self.driver].name) if counts else None

    # ---------------------------------------------------------------- discovery

    def _open(self) -> IO[bytes]:
        try:
            return open(self.path, "rb")
        except OSError as error:
            raise FrontendInputError(f"{self.path}: cannot open MCAP ({error})") from None

    def _discover(self) -> tuple[bool, list[tuple[Channel, str]], dict[str, int]]:
        """Channels and their types, from the summary or (unindexed log) a linear scan."""
        with self._open() as stream:
            try:
                reader = SeekingReader(stream)
            except McapError as error:  # bad or missing magic bytes
                raise FrontendInputError(f"{self.path}: not an MCAP file ({error})") from None
            try:
                summary = reader.get_summary()
            except Exception as error:  # missing/cut footer, corrupt summary: read linearly
                log.debug("%s: no usable summary (%s)", self.path, error)
                summary = None
            if summary is not None and summary.chunk_indexes:
                channels = [(c, self._type(summary.schemas.get(c.schema_id))) for c in summary.channels.values()]
                counts: dict[str, int] = {}
                if summary.statistics is not None:
                    for cid, n in summary.statistics.channel_message_counts.items():
                        topic = summary.channels[cid].topic
                        counts[topic] = counts.get(topic, 0) + n
                return True, channels, counts
            stream.seek(0)
            return False, self._scan_channels(stream), {}

    def _scan_channels(self, stream: IO[bytes]) -> list[tuple[Channel, str]]:
        schemas: dict[int, Schema] = {}
        channels: list[tuple[Channel, str]] = []
        try:
            for record in StreamReader(stream).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels.append((record, self._type(schemas.get(record.schema_id))))
        except Exception as error:  # cut or corrupt: reported while reading frames, or below if no topic was seen
            log.debug("%s: channel scan stopped early: %s", self.path, error)
            self._scan_stopped = f"{type(error).__name__}: {error}" if str(error) else type(error).__name__
        return channels

    @staticmethod
    def _type(schema: Schema | None) -> str:
        return normalise_type(schema.name) if schema is not None else "(no schema)"

    def _select_topics(self, present: dict[str, str]) -> dict[str, _Topic]:
        listing = ", ".join(f"{t} ({present[t]})" for t in sorted(present)) or "none"
        chosen: dict[str, _Topic] = {}
        for role, (accepted, auto_types, defaults) in ROLES.items():
            requested = getattr(self.config, ROLE_CONFIG_FIELD[role])
            if requested == "":
                continue
            if requested is not None:
                if requested not in present:
                    raise FrontendInputError(
                        f"{self.path}: {role} topic '{requested}' not found; topics present: {listing}"
                    )
                if present[requested] not in accepted:
                    raise FrontendInputError(
                        f"{self.path}: {role} topic '{requested}' has type {present[requested]}, "
                        f"expected one of {', '.join(accepted)}"
                    )
                chosen[role] = _Topic(role, requested, present[requested])
                continue
            taken = {t.name for t in chosen.values()} | {
                getattr(self.config, f) for f in ROLE_CONFIG_FIELD.values() if getattr(self.config, f)
            }
            candidates = [t for t in present if present[t] in auto_types and t not in taken]
            if role == "rear_camera":
                candidates = [t for t in candidates if t in defaults]
            elif role == "camera":
                candidates = [t for t in candidates if t not in ROLES["rear_camera"][2]]
            if not candidates:
                continue
            # Prefer our writer's names, then type order (raw before compressed), then name.
            candidates.sort(key=lambda t: (t not in defaults, auto_types.index(present[t]), t))
            if len(candidates) > 1:
                log.info("%s: %s topics %s; using %s", self.path, role, candidates, candidates[0])
            chosen[role] = _Topic(role, candidates[0], present[candidates[0]])
        if "camera" not in chosen and "lidar" not in chosen:
            if self._scan_stopped is not None:
                raise FrontendInputError(
                    f"{self.path}: log is truncated or corrupt before any camera or LiDAR topic "
                    f"({self._scan_stopped}); topics read: {listing}"
                )
            raise FrontendInputError(
                f"{self.path}: no camera (Image/CompressedImage) or LiDAR (PointCloud2) topic; "
                f"topics present: {listing}"
            )
        return chosen

    def _pick_driver(self) -> str:
        drive = self.config.drive
        if drive == "auto":
            return "camera" if "camera" in self._roles else "lidar"
        if drive not in self._roles:
            raise FrontendInputError(f"{self.path}: drive='{drive}' but the log has no {drive} topic")
        return drive

    # ---------------------------------------------------------------- Source API

    @property
    def length(self) -> int | None:
        """Messages on the driving topic (an upper bound: skipped messages make no frame)."""
        return self._length

    @property
    def topics(self) -> dict[str, str]:
        return {role: f"{t.name} ({t.type})" for role, t in self._roles.items()}

    @property
    def description(self) -> str:
        streams = ", ".join(f"{r}={t.name}" for r, t in self._roles.items())
        return f"MCAP {self.path.name}: driven by {self.driver}; {streams}"

    def __iter__(self) -> Iterator[Frame]:
        self.reset_stats()
        cfg = self.config
        aux = [r for r in self._roles if r != self.driver]
        associator = StreamAssociator(
            aux,
            cfg.association_tolerance_s,
            cfg.max_latency_s,
            cfg.max_pending_frames,
            cfg.max_buffered_messages,
            self.stats,
        )
        by_topic = {t.name: t for t in self._roles.values()}
        clock = StreamClock(self.stats, cfg.max_time_gap_s)
        factory = DecoderFactory()
        failure: str | None = None
        with self._open() as stream:
            messages = self._raw_messages(stream, list(by_topic))
            while True:
                try:
                    item = next(messages)
                except StopIteration:
                    break
                except Exception as error:  # the reader hit a cut or corrupt record
                    failure = type(error).__name__ + (f": {error}" if str(error) else "")
                    break
                schema, channel, message = item
                topic = by_topic[channel.topic]
                decoded = self._decode(factory, schema, channel, message)
                if decoded is None:
                    continue
                time = self._time(decoded, message)
                if not clock.accept(topic.role, time, f"{self.path}: {topic.name}"):
                    continue
                payload = self._convert(topic, decoded, time)
                if payload is None and (topic.role != self.driver or not aux):
                    continue  # a bad driving message still makes a frame for the other sensors
                if topic.role == self.driver:
                    ready = associator.add_driver(time, payload)
                else:
                    ready = associator.add_aux(topic.role, time, payload)
                yield from self._frames(ready)
        yield from self._frames(associator.flush())
        if failure is not None:
            why = f"{self.path}: log is truncated or corrupt after {self.stats.frames_yielded} frames ({failure})"
            if cfg.strict:
                raise FrontendInputError(why)
            self.stats.skip("truncated", why + "; stopping (strict=False)")

    # ---------------------------------------------------------------- helpers

    def _raw_messages(self, stream: IO[bytes], topics: list[str]) -> Iterator[tuple[Schema | None, Channel, Message]]:
        if self._indexed:
            reader = SeekingReader(stream)
            back = _goes_back_in_file_order(stream, reader.get_summary(), set(topics))
            if back is None:
                return reader.iter_messages(topics=topics, log_time_order=True)
            # Sorting by log time would interleave the parts before and after the jump.
            self.stats.warn(
                "clock_went_back",
                f"{self.path}: {back[0]} log time goes back {back[1]:.3f} s in file order; "
                "reading in file order, messages before the time passes again are skipped",
            )
            stream.seek(0)
            return reader.iter_messages(topics=topics, log_time_order=False)
        # File order: sorting an unindexed log by time would load all of it into memory.
        return NonSeekingReader(stream).iter_messages(topics=topics, log_time_order=False)

    def _decode(self, factory: DecoderFactory, schema: Schema | None, channel: Channel, message: Message) -> Any:
        try:
            decoder = factory.decoder_for(channel.message_encoding, schema)
            if decoder is None:
                raise FrontendInputError(
                    f"{self.path}: {channel.topic} uses encoding '{channel.message_encoding}' "
                    "without a ros2msg schema; only ROS 2 CDR messages are supported"
                )
            return decoder(message.data)
        except FrontendInputError:
            raise
        except Exception as error:
            self.stats.skip(
                "undecodable_message",
                f"{self.path}: cannot decode a {channel.topic} message ({error})",
            )
            return None

    def _time(self, decoded: Any, message: Message) -> float:
        header = getattr(decoded, "header", None)
        if self.config.use_header_stamp and header is not None:
            stamp = ros_convert.stamp_seconds(header.stamp)
            if stamp > 0:
                return stamp
        return message.log_time / ros_convert.NANOSECONDS

    def _convert(self, topic: _Topic, decoded: Any, time: float) -> Any:
        """Message -> numpy payload for the Frame; None (counted, first one warned) when unusable.

        One bad message never stops a stream: it is skipped, naming topic, time and reason.
        """
        where = f"{self.path}: {topic.name} at t={time:.6f}"
        try:
            if topic.type == IMAGE:
                return ros_convert.decode_image(decoded, where)
            if topic.type == COMPRESSED_IMAGE:
                image = ros_convert.decode_compressed_image(decoded, where)
                if image is None:
                    raise FrontendInputError(f"{where}: compressed image cannot be decoded")
                return image
            if topic.type == POINT_CLOUD2:
                return ros_convert.decode_point_cloud(decoded, where)
            pose = ros_convert.decode_pose(decoded, where)
        except FrontendInputError as error:
            if topic.role in _CAMERA_ROLES and not self.config.skip_undecodable_images:
                raise
            reason = "undecodable_image" if topic.role in _CAMERA_ROLES else f"bad_{topic.role}"
            self.stats.skip(reason, f"{error}; message skipped")
            return None
        problem = pose_problem(pose, self._rotation_tolerance)
        if problem is not None:
            self.stats.skip(f"invalid_{topic.role}", f"{where}: {problem}; message skipped")
            return None
        return self.plausible_pose(topic.role, pose, time, where)

    def _frames(self, ready: list[Associated]) -> Iterator[Frame]:
        for item in ready:
            parts = dict(item.matches)
            parts[self.driver] = item.payload
            points, times = parts.get("lidar") or (None, None)
            frame = Frame(
                index=self.stats.frames_yielded,
                timestamp=item.time,
                image=parts.get("camera"),
                rear_image=parts.get("rear_camera"),
                points=points,
                point_times=times,
                logged_pose=parts.get("logged_pose"),
                gt_pose=parts.get("gt_pose"),
            )
            self.stats.frames_yielded += 1
            yield frame


def _goes_back_in_file_order(stream: IO[bytes], summary: Summary | None, topics: set[str]) -> tuple[str, float] | None:
    """(topic, seconds) of the largest backward step of a topic's log time in file order.

    Read from the chunks' message index records (times and offsets, no decompression), so
    even a multi-gigabyte log is checked in a moment. None when every topic only goes forward.
    """
    if summary is None:
        return None
    worst: tuple[str, float] | None = None
    last: dict[int, int] = {}
    for chunk in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        for channel_id, offset in sorted(chunk.message_index_offsets.items()):
            channel = summary.channels.get(channel_id)
            if channel is None or channel.topic not in topics:
                continue
            stream.seek(offset + 1 + 8)  # opcode and record length precede the record
            index = MessageIndex.read(ReadDataStream(stream))
            for log_time, _ in sorted(index.records, key=lambda r: r[1]):  # by offset: file order
                previous = last.get(channel_id)
                if previous is not None and log_time < previous:
                    step = (previous - log_time) / ros_convert.NANOSECONDS
                    if worst is None or step > worst[1]:
                        worst = (channel.topic, step)
                last[channel_id] = max(log_time, previous or log_time)
    return worst
