"""A log as a loop-eval sequence: its camera frames, one keyframe every so many metres of its
own ground truth (the run's keyframe rule applied to the true path), judged against that truth.

A log is read twice: once for the ground truth (which frames are keyframes, where they are:
the truth is built before the backbone loads), once for the images, so a long log is never held
in memory. Its LiDAR is not read: recognition is judged on the images alone."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from frontend.keyframes import KeyframeSelector
from frontend.sources import open_source
from frontend.sources.base import Source
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.loop_eval.revisit_truth import LoopTruthError
from ssmvpr_slam.loop_eval.stream import ImagePair


@dataclass(frozen=True)
class LogKeyframes:
    """The frames of a log that loop-eval streams."""

    log: Path
    frame_indices: tuple[int, ...]  # the source's frame index of each keyframe
    poses: np.ndarray  # (N, 4, 4) ground truth of each keyframe
    has_rear: bool

    def names(self) -> list[str]:
        return [f"{self.log.name}#{i}" for i in self.frame_indices]


def _open(log: Path, config: SlamConfig) -> Source:
    source_config = config.frontend.source.model_copy(deep=True)
    source_config.mcap = source_config.mcap.model_copy(update={"lidar_topic": ""})  # images only
    source_config.kitti = source_config.kitti.model_copy(update={"load_points": False})
    return open_source(log, source_config, config.frontend.pose_files)


def keyframes_of(log: Path, config: SlamConfig) -> LogKeyframes:
    """First pass: the frames with an image and a ground-truth pose, thinned by
    `frontend.keyframes` along the ground truth."""
    source = _open(log, config)
    if "camera" not in source.topics:
        raise LoopTruthError(f"{log}: no camera images to recognise places in (streams: {', '.join(source.topics)})")
    if "gt_pose" not in source.topics:
        raise LoopTruthError(f"{log}: no ground-truth poses to judge loops by (streams: {', '.join(source.topics)}); "
                             "give image folders with --gt-poses instead")  # fmt: skip
    selector = KeyframeSelector(config.frontend.keyframes)
    indices: list[int] = []
    poses: list[np.ndarray] = []
    has_rear = False
    for frame in source:
        if frame.image is None or frame.gt_pose is None:
            continue
        if selector.select(frame.gt_pose, frame.timestamp):
            indices.append(frame.index)
            poses.append(frame.gt_pose)
            has_rear = has_rear or frame.rear_image is not None
    if not indices:
        raise LoopTruthError(f"{log}: no frame has both a camera image and a ground-truth pose")
    return LogKeyframes(log, tuple(indices), np.array(poses), has_rear)


def images_of_log(keyframes: LogKeyframes, config: SlamConfig) -> Iterator[ImagePair]:
    """Second pass: the keyframes' images, in order (a rear image when the log has a rear camera)."""
    wanted = iter(keyframes.frame_indices)
    target = next(wanted, None)
    for frame in _open(keyframes.log, config):
        if target is None:
            return
        if frame.index != target:
            continue
        assert frame.image is not None
        yield frame.image, frame.rear_image if keyframes.has_rear else None
        target = next(wanted, None)
    if target is not None:
        raise LoopTruthError(f"{keyframes.log}: ended before frame {target} on the second reading")
