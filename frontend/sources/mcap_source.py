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
from collections.abc import Generator, Iterator
from pathlib import Path
from typing import IO, Any

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.records import Channel, Message, MessageIndex, Schema
from mcap.stream_reader import StreamReader
from mcap.summary import Summary
from mcap_ros2.decoder import DecoderFactory

from frontend.config import McapSourceConfig, PoseFileConfig
from frontend.errors import FrontendInputError
from frontend.sources import ros_convert
from frontend.sources.ros_msgdefs import normalise_type
from frontend.sources.ros_stream import ROLE_CONFIG_FIELD, ROLES, RosStreamSource

log = logging.getLogger("frontend.sources.mcap")

__all__ = ["ROLES", "ROLE_CONFIG_FIELD", "McapSource"]


class McapSource(RosStreamSource):
    """Frames from an MCAP log; see the module docstring for how streams are combined."""

    kind = "MCAP"

    def __init__(
        self,
        path: str | Path,
        config: McapSourceConfig | None = None,
        pose_config: PoseFileConfig | None = None,
    ) -> None:
        super().__init__(Path(path), config, pose_config)
        if not self.path.is_file():
            raise FrontendInputError(f"{self.path}: MCAP file not found")
        self._indexed, channels, counts = self._discover()
        self._choose_streams({c.topic: t for c, t in channels}, counts)

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

    # ---------------------------------------------------------------- messages

    def _decoded(self, topics: list[str]) -> Generator[tuple[str, int, Any]]:
        factory = DecoderFactory()
        with self._open() as stream:
            for schema, channel, message in self._raw_messages(stream, topics):
                yield channel.topic, message.log_time, self._decode(factory, schema, channel, message)

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
