"""Stream Frames out of a ROS 1 bag (``.bag``) or a ROS 2 bag folder (``metadata.yaml`` with
``.db3`` or ``.mcap`` storage), read through `rosbags` (pure Python, no ROS install), with the
same topic selection, clock and bad-message rules as an MCAP log (`frontend.source.mcap`
settings apply to bags too; see :mod:`frontend.sources.ros_stream`)."""

from __future__ import annotations

from collections.abc import Generator, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader

from frontend.config import McapSourceConfig, PoseFileConfig
from frontend.errors import FrontendInputError
from frontend.sources.ros_msgdefs import normalise_type
from frontend.sources.ros_stream import RosStreamSource

BAG_SUFFIX = ".bag"
ROS2_METADATA = "metadata.yaml"


def is_rosbag(path: Path) -> bool:
    """A ROS 1 bag file, or a ROS 2 bag folder."""
    return (path.is_file() and path.suffix.lower() == BAG_SUFFIX) or (
        path.is_dir() and (path / ROS2_METADATA).is_file()
    )


class RosbagSource(RosStreamSource):
    """Frames from a ROS 1 or ROS 2 bag."""

    def __init__(
        self, path: str | Path, config: McapSourceConfig | None = None, pose_config: PoseFileConfig | None = None
    ) -> None:
        super().__init__(Path(path), config, pose_config)
        if not self.path.exists():
            raise FrontendInputError(f"{self.path}: ROS bag not found")
        self.kind = "ROS 1 bag" if self.path.is_file() else "ROS 2 bag"
        with self._reader() as reader:
            present = {c.topic: normalise_type(c.msgtype) for c in reader.connections}
            counts: dict[str, int] = {}
            for c in reader.connections:
                counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        self._choose_streams(present, counts)

    @contextmanager
    def _reader(self) -> Iterator[AnyReader]:
        """The bag, open; one that cannot be opened (cut, corrupt, not a bag) is one error line."""
        reader = AnyReader([self.path])
        try:
            reader.open()
        except Exception as error:  # rosbags' ReaderError and what the storage below it raises
            raise FrontendInputError(f"{self.path}: cannot read this {self.kind} ({error})") from None
        try:
            yield reader
        finally:
            reader.close()

    def _decoded(self, topics: list[str]) -> Generator[tuple[str, int, Any]]:
        wanted = set(topics)
        with self._reader() as reader:
            connections = [c for c in reader.connections if c.topic in wanted]
            for connection, timestamp, raw in reader.messages(connections=connections):
                yield connection.topic, timestamp, self._deserialize(reader, connection, raw)

    def _deserialize(self, reader: AnyReader, connection: Any, raw: bytes) -> Any:
        try:
            return reader.deserialize(raw, connection.msgtype)
        except Exception as error:
            self.stats.skip("undecodable_message", f"{self.path}: cannot decode a {connection.topic} message ({error})")
            return None
