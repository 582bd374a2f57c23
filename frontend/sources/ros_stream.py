"""What every ROS log source shares (MCAP files, ROS 1 and ROS 2 bags): topics found by message
type (or named in the config), the camera stream driving the frames (the LiDAR when there is no
camera) and the other streams matched by nearest timestamp (:mod:`frontend.sources.association`),
messages turned into numpy payloads (:mod:`frontend.sources.ros_convert`), one bad message
skipped and counted, a cut log reported after every frame before it. Each camera's calibration
is the first message of its CameraInfo topic (`intrinsics`), read only when asked for.

A subclass finds the log's topics (`present`, message counts) and yields its decoded messages in
time order (`_decoded`); everything from there to frames is here.
"""

from __future__ import annotations

import logging
import posixpath
from abc import abstractmethod
from collections.abc import Generator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from frontend.config import McapSourceConfig, McapWriterConfig, PoseFileConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.sources import ros_convert
from frontend.sources.association import Associated, StreamAssociator
from frontend.sources.base import Source, SourceStats
from frontend.sources.clock import StreamClock, time_problem
from frontend.sources.intrinsics import CameraIntrinsics
from frontend.sources.ros_msgdefs import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    IMAGE,
    ODOMETRY,
    POINT_CLOUD2,
    POSE_STAMPED,
)
from ssmvpr_common.poses import pose_problem

log = logging.getLogger("frontend.sources.ros")

POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
CLOCK_PROBE_MESSAGES = 2000
"""Messages read ahead to find every chosen topic's first time (the clock is chosen from them)."""
UNSET_STAMP_LOG_TIME_S = 1.0
"""A stamp of 0 is unset when the message's log time is past this (a log may start at time 0)."""
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


def camera_info_candidates(image_topic: str, image_type: str) -> list[str]:
    """Where a camera's CameraInfo is, by ROS convention: beside its image topic
    (/camera/image_raw -> /camera/camera_info), and for a compressed transport also beside the
    topic it compresses (/camera/image_raw/compressed -> .../image_raw/camera_info, /camera/camera_info)."""
    parent = posixpath.dirname(image_topic)
    candidates = [posixpath.join(parent, "camera_info")]
    if image_type == COMPRESSED_IMAGE:
        candidates.append(posixpath.join(posixpath.dirname(parent), "camera_info"))
    return candidates


@dataclass
class Topic:
    role: str
    name: str
    type: str


class RosStreamSource(Source):
    """Frames from a log of ROS messages; `kind` names the format in messages ("MCAP", "ROS 1 bag")."""

    kind = "ROS log"

    def __init__(self, path: Path, config: McapSourceConfig | None, pose_config: PoseFileConfig | None) -> None:
        super().__init__()
        self.path = path
        self.config = config or McapSourceConfig()
        self._rotation_tolerance = (pose_config or PoseFileConfig()).rotation_tolerance
        self._scan_stopped: str | None = None  # why a linear topic scan ended early (cut or corrupt log)
        self._header_clock = self.config.use_header_stamp
        self._clock_warning: str | None = None
        self._info_topics: dict[str, str] = {}  # camera role -> its CameraInfo topic
        self._intrinsics: dict[str, CameraIntrinsics] | None = None  # read on first use

    def _choose_streams(self, present: dict[str, str], counts: dict[str, int] | None) -> None:
        """Select each role's topic among `present` ({topic: normalised type}) and the driver."""
        self._roles = self._select_topics(present)
        self._info_topics = self._select_info_topics(present)
        self.driver = self._pick_driver()
        self._length = counts.get(self._roles[self.driver].name) if counts else None
        self._header_clock, self._clock_warning = self._choose_clock([t.name for t in self._roles.values()])

    @abstractmethod
    def _decoded(self, topics: list[str]) -> Generator[tuple[str, int, Any]]:
        """(topic, log time in ns, decoded message or None when it could not be decoded), in
        time order; an exception means the log is cut or corrupt there."""

    def _select_topics(self, present: dict[str, str]) -> dict[str, Topic]:
        listing = ", ".join(f"{t} ({present[t]})" for t in sorted(present)) or "none"
        chosen: dict[str, Topic] = {}
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
                chosen[role] = Topic(role, requested, present[requested])
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
            chosen[role] = Topic(role, candidates[0], present[candidates[0]])
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

    def _select_info_topics(self, present: dict[str, str]) -> dict[str, str]:
        """Each camera's CameraInfo topic: named in the config (checked like any named topic), or
        the one beside its image topic (`camera_info_candidates`) unless both cameras' are the same."""
        named: dict[str, str] = {}
        automatic: dict[str, str] = {}
        for role in _CAMERA_ROLES:
            requested = getattr(self.config, f"{role}_info_topic")
            if role not in self._roles or requested == "":
                continue
            if requested is not None:
                if present.get(requested) != CAMERA_INFO:
                    found = f"has type {present[requested]}" if requested in present else "not found"
                    raise FrontendInputError(
                        f"{self.path}: {role} info topic '{requested}' {found}; expected a {CAMERA_INFO} topic "
                        f"(topics present: {', '.join(sorted(present)) or 'none'})"
                    )
                named[role] = requested
                continue
            image = self._roles[role]
            beside = [t for t in camera_info_candidates(image.name, image.type) if present.get(t) == CAMERA_INFO]
            if beside:
                automatic[role] = beside[0]
        chosen = dict(named)
        for role, topic in automatic.items():
            if topic in [t for r, t in {**named, **automatic}.items() if r != role]:
                self.calibration_warning(
                    "ambiguous_calibration",
                    f"{self.path}: {topic} is beside both cameras' topics; not used for the {role} "
                    f"(name it in {role}_info_topic)",
                )
                continue
            chosen[role] = topic
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
    def intrinsics(self) -> dict[str, CameraIntrinsics]:
        """Each camera's K from the first message of its CameraInfo topic (config
        ``camera_info_topic``, ``rear_camera_info_topic``), read on first use: a log with none has
        none, an unusable one is a counted warning."""
        if self._intrinsics is None:
            self._intrinsics = {}
            for role, topic in self._info_topics.items():
                found = self._read_calibration(topic)
                if found is not None:
                    self._intrinsics[role] = found
        return dict(self._intrinsics)

    @property
    def description(self) -> str:
        streams = ", ".join(f"{r}={t.name}" for r, t in self._roles.items())
        return f"{self.kind} {self.path.name}: driven by {self.driver}; {streams}"

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
        if self._clock_warning is not None:
            self.stats.warn("clock_log_time", self._clock_warning)
        clock = StreamClock(self.stats, cfg.max_time_gap_s)
        failure: str | None = None
        messages = self._decoded(list(by_topic))
        try:
            while True:
                try:
                    name, log_time, decoded = next(messages)
                except StopIteration:
                    break
                except FrontendInputError:
                    raise
                except Exception as error:  # the reader hit a cut or corrupt record
                    failure = type(error).__name__ + (f": {error}" if str(error) else "")
                    break
                if decoded is None:
                    continue
                topic = by_topic[name]
                time = self._time(decoded, log_time)
                if time is None:
                    self.stats.skip(
                        f"unset_stamp_{topic.role}",
                        f"{self.path}: {topic.name} message with header stamp 0 in a log timed by header "
                        "stamps; skipped",
                    )
                    continue
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
        finally:
            messages.close()  # the reader holding the log open lets go of it now
        yield from self._frames(associator.flush())
        if failure is not None:
            why = f"{self.path}: log is truncated or corrupt after {self.stats.frames_yielded} frames ({failure})"
            if cfg.strict:
                raise FrontendInputError(why)
            self.stats.skip("truncated", why + "; stopping (strict=False)")

    # ---------------------------------------------------------------- helpers

    def _read_calibration(self, topic: str) -> CameraIntrinsics | None:
        where = f"{self.path}: {topic}"
        try:
            values, width, height = ros_convert.decode_camera_info(self._first_message(topic), where)
        except FrontendInputError as error:
            self.calibration_warning("unreadable_calibration", f"{error}; calibration ignored")
            return None
        except Exception as error:  # a cut or corrupt log: the frames' pass reports where
            self.calibration_warning(
                "unreadable_calibration", f"{where}: cannot be read ({error!r}); calibration ignored"
            )
            return None
        return self.calibration(values, width, height, where)

    def _first_message(self, topic: str) -> Any:
        """The topic's first decoded message, reading no further; what the reader notes on the
        way (a clock going back, say) is the frames' pass to count and tell."""
        counting, self.stats = self.stats, SourceStats(quiet=True)
        messages = self._decoded([topic])
        try:
            for _, _, decoded in messages:
                if decoded is None:
                    raise FrontendInputError(f"{self.path}: {topic}: its first message cannot be decoded")
                return decoded
        finally:
            messages.close()
            self.stats = counting
        raise FrontendInputError(f"{self.path}: {topic} has no message")

    @staticmethod
    def _stamp(decoded: Any, log_time: float) -> float | None:
        """The message's header stamp in seconds; None when it has none or it is unset: 0 (or
        less) while the log time is not (a recorder that leaves stamps at 0 but logs wall-clock
        time); a log that starts at time 0 on both clocks is stamped, not unset."""
        header = getattr(decoded, "header", None)
        if header is None:
            return None
        stamp = ros_convert.stamp_seconds(header.stamp)
        return stamp if stamp > 0 or log_time < UNSET_STAMP_LOG_TIME_S else None

    def _choose_clock(self, topics: list[str]) -> tuple[bool, str | None]:
        """One clock for the whole log, from each topic's first message, chosen when the log is
        opened: header stamps when every topic's first stamp is set, else log time for every topic
        (the warning to tell as the log is read). Frames never mix the two clocks, and a log whose
        times no writer can hold is refused here, before any work."""
        first: dict[str, tuple[float | None, float]] = {}
        counting, self.stats = self.stats, SourceStats(quiet=True)  # the real pass counts and tells
        messages = self._decoded(topics)
        try:
            for count, (name, log_time, decoded) in enumerate(messages):
                if decoded is not None and name not in first:
                    seconds = log_time / ros_convert.NANOSECONDS
                    first[name] = (self._stamp(decoded, seconds), seconds)
                if len(first) == len(topics) or count >= CLOCK_PROBE_MESSAGES:
                    break
        except FrontendInputError:
            raise
        except Exception:  # a cut log: the main pass reports where
            pass
        finally:
            messages.close()
            self.stats = counting
        header = self.config.use_header_stamp and bool(first)
        unset = sorted(name for name, (stamp, _) in first.items() if stamp is None)
        warning = None
        if header and unset:
            header = False
            warning = (
                f"{self.path}: header stamps of {', '.join(unset)} start unset (0); every topic is timed "
                "by log time instead (one clock for the whole log)"
            )
        for name, (stamp, logged) in first.items():
            time = stamp if header and stamp is not None else logged
            problem = time_problem(time)
            if problem is not None:
                clock = "header stamp" if header else "log time"
                raise FrontendInputError(f"{self.path}: {name} {clock}: {problem}; refusing the log")
        return header, warning

    def _time(self, decoded: Any, log_time_ns: int) -> float | None:
        """The message's time on the log's clock; None for an unset stamp on a header-stamped log."""
        log_time = log_time_ns / ros_convert.NANOSECONDS
        return self._stamp(decoded, log_time) if self._header_clock else log_time

    def _convert(self, topic: Topic, decoded: Any, time: float) -> Any:
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
