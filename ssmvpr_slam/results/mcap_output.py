"""trajectory.mcap: a run's result as ROS 2 messages that Foxglove (or any MCAP reader) opens.

Topics (frame ``map``, the session's optimised frame; times are the keyframes' log times):

- ``/slam/odometry/path``, ``/slam/optimised/path`` (nav_msgs/Path): the whole keyframe
  trajectories, once, at the first keyframe's time, so they are on screen wherever the
  playhead is;
- ``/slam/odometry/pose``, ``/slam/optimised/pose`` (geometry_msgs/PoseStamped): one per
  keyframe, to follow the run along the timeline;
- ``/slam/loops`` (visualization_msgs/MarkerArray): loop edges between optimised keyframe
  positions (green: in the graph, red: gate-accepted but rejected by registration or GNC), once
  at the first keyframe's time; loops spaced out by `loop_spacing_keyframes` (never registered)
  and prior-map loops (their other end is in another session's frame) are not drawn;
- ``/slam/keyframes/image/compressed`` (sensor_msgs/CompressedImage, JPEG): a thumbnail per
  keyframe (made when the keyframe was selected, `ssmvpr_slam.thumbnail`: the run keeps no full image).

Written through the frontend's MCAP writer: a temp file renamed into place on a clean close.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from frontend.config import McapWriterConfig
from frontend.sources import ros_convert, ros_msgdefs
from frontend.sources.mcap_writer import McapFrameWriter
from ssmvpr_slam.run_result import RunResult

FRAME = "map"
ODOMETRY_PATH = "/slam/odometry/path"
OPTIMISED_PATH = "/slam/optimised/path"
ODOMETRY_POSE = "/slam/odometry/pose"
OPTIMISED_POSE = "/slam/optimised/pose"
LOOPS = "/slam/loops"
THUMBNAILS = "/slam/keyframes/image/compressed"
TOPICS = (ODOMETRY_PATH, OPTIMISED_PATH, ODOMETRY_POSE, OPTIMISED_POSE, LOOPS, THUMBNAILS)

_IN_GRAPH = (0.1, 0.8, 0.2, 1.0)
_REJECTED = (0.9, 0.2, 0.2, 0.8)

log = logging.getLogger(__name__)


def write_trajectory_mcap(path: Path, result: RunResult) -> Path | None:
    """Write the run's trajectories, loop edges and keyframe thumbnails; None without keyframes."""
    kfs = result.keyframes
    if not kfs:
        return None
    stamps = np.asarray(result.stamps, np.float64)
    start = float(stamps[0])
    with McapFrameWriter(path, McapWriterConfig(compression="zstd")) as writer:
        writer.write_message(
            ODOMETRY_PATH, ros_msgdefs.PATH, ros_convert.path_message(result.odometry, stamps, FRAME), start
        )
        writer.write_message(
            OPTIMISED_PATH, ros_msgdefs.PATH, ros_convert.path_message(result.optimised, stamps, FRAME), start
        )
        writer.write_message(LOOPS, ros_msgdefs.MARKER_ARRAY, _loop_markers(result, start), start)
        for kf, t, odom, opt in zip(kfs, stamps.tolist(), result.odometry, result.optimised):
            writer.write_message(
                ODOMETRY_POSE, ros_msgdefs.POSE_STAMPED, ros_convert.pose_stamped_message(odom, t, FRAME), t
            )
            writer.write_message(
                OPTIMISED_POSE, ros_msgdefs.POSE_STAMPED, ros_convert.pose_stamped_message(opt, t, FRAME), t
            )
            if kf.thumbnail is not None:
                message = ros_convert.encoded_image_message(kf.thumbnail, t, f"keyframe_{kf.id}", "jpeg")
                writer.write_message(THUMBNAILS, ros_msgdefs.COMPRESSED_IMAGE, message, t)
    return path


def _loop_markers(result: RunResult, seconds: float) -> dict[str, object]:
    """Two LINE_LIST markers: loops in the graph and gate-accepted loops that are not."""
    positions = np.asarray(result.optimised)[:, :3, 3]
    kept: list[tuple[np.ndarray, np.ndarray]] = []
    rejected: list[tuple[np.ndarray, np.ndarray]] = []
    for record in result.session_loops:
        p = record.proposal
        if not p.accepted or record.spaced:  # a spaced loop was not registered: neither kept nor rejected
            continue
        segment = (positions[p.match_id], positions[p.query_id])
        (kept if record.in_graph else rejected).append(segment)
    markers = [
        ros_convert.line_list_marker(kept, seconds, FRAME, "loops_in_graph", 0, _IN_GRAPH, 0.3),
        ros_convert.line_list_marker(rejected, seconds, FRAME, "loops_rejected", 1, _REJECTED, 0.15),
    ]
    return {"markers": markers}
