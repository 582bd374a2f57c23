"""trajectory.mcap reads back with the `mcap` reader: every topic, its schema and its content."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from loopclosure.detector import LoopProposal
from ssmvpr_slam import thumbnail
from ssmvpr_slam.results import mcap_output
from ssmvpr_slam.run_result import Keyframe, LoopRecord, RunResult

N = 12


def _result() -> RunResult:
    """A square drive of 12 keyframes with a loop in the graph (11 -> 0) and one rejected (6 -> 1)."""
    odom = np.tile(np.eye(4), (N, 1, 1))
    odom[:, 0, 3] = np.arange(N) * 2.0
    optimised = odom.copy()
    optimised[:, 1, 3] = 0.1 * np.arange(N)
    rng = np.random.default_rng(0)

    def jpeg() -> bytes:
        return thumbnail.thumbnail_jpeg(rng.integers(0, 256, (240, 320, 3), dtype=np.uint8), 80)

    kfs = tuple(Keyframe(k, 2 * k, 10.0 + k, odom[k], None, None, None, thumbnail=jpeg()) for k in range(N))
    proposal = LoopProposal(11, 0, 0, 0.8, 0.5, 0, 0.0, True, "accepted", "forward")
    rejected = LoopProposal(6, 1, 1, 0.7, 0.5, 0, 0.0, True, "accepted", "forward")
    not_accepted = LoopProposal(7, 2, 2, 0.3, 0.2, 0, 0.0, False, "sequence score too low", "forward")
    loops = (LoopRecord(rejected), LoopRecord(not_accepted), LoopRecord(proposal, factor_handle=0))
    return RunResult(kfs, loops, np.arange(N) + 10.0, odom, optimised)


def _read(path: Path) -> dict[str, list[tuple[str, int, object]]]:
    """topic -> [(schema name, log time ns, decoded message)]."""
    out: dict[str, list[tuple[str, int, object]]] = defaultdict(list)
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
            out[channel.topic].append((schema.name, message.log_time, decoded))
    return out


def test_every_topic_reads_back(tmp_path: Path) -> None:
    result = _result()
    path = mcap_output.write_trajectory_mcap(tmp_path / "trajectory.mcap", result)
    assert path is not None and not list(tmp_path.glob(".*"))  # no temp file left behind
    topics = _read(path)
    assert set(topics) == set(mcap_output.TOPICS)

    for topic, poses in ((mcap_output.ODOMETRY_PATH, result.odometry), (mcap_output.OPTIMISED_PATH, result.optimised)):
        [(schema, log_time, msg)] = topics[topic]
        assert schema == "nav_msgs/msg/Path" and log_time == 10_000_000_000 and msg.header.frame_id == "map"
        xyz = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in msg.poses])
        np.testing.assert_allclose(xyz, poses[:, :3, 3])
        assert [p.header.stamp.sec for p in msg.poses] == list(range(10, 10 + N))

    for topic in (mcap_output.ODOMETRY_POSE, mcap_output.OPTIMISED_POSE):
        assert [s for s, _, _ in topics[topic]] == ["geometry_msgs/msg/PoseStamped"] * N
        assert [t for _, t, _ in topics[topic]] == [(10 + k) * 1_000_000_000 for k in range(N)]
    last = topics[mcap_output.OPTIMISED_POSE][-1][2]
    assert last.pose.position.y == np.float64(0.1 * (N - 1)) and last.pose.orientation.w == 1.0

    [(schema, _, markers)] = topics[mcap_output.LOOPS]
    assert schema == "visualization_msgs/msg/MarkerArray"
    kept, rejected = markers.markers
    assert kept.type == rejected.type == 5 and kept.ns == "loops_in_graph"
    np.testing.assert_allclose([(p.x, p.y, p.z) for p in kept.points], [(0.0, 0.0, 0.0), (22.0, 1.1, 0.0)])
    assert len(rejected.points) == 2  # 6 -> 1: accepted by the gate, never a factor; 7 -> 2 not drawn

    thumbs = topics[mcap_output.THUMBNAILS]
    assert [s for s, _, _ in thumbs] == ["sensor_msgs/msg/CompressedImage"] * N
    image = cv2.imdecode(np.frombuffer(bytes(thumbs[0][2].data), np.uint8), cv2.IMREAD_COLOR)
    assert thumbs[0][2].format == "jpeg" and image.shape == (60, 80, 3)
    assert bytes(thumbs[0][2].data) == result.keyframes[0].thumbnail  # written as kept, not encoded again


def test_a_run_without_keyframes_writes_no_mcap(tmp_path: Path) -> None:
    empty = RunResult((), (), np.zeros(0), np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))
    assert mcap_output.write_trajectory_mcap(tmp_path / "trajectory.mcap", empty) is None
    assert not list(tmp_path.iterdir())
