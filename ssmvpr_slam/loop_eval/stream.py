"""Image sequences through the detector `run` builds, one keyframe per image."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from loopclosure.backbone import Backbone
from loopclosure.backbone_input import read_image
from loopclosure.detector import LoopProposal
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.system import build_detector


@dataclass(frozen=True)
class StreamOutcome:
    proposals: tuple[LoopProposal | None, ...]  # per stream frame: its best sequence and the decision
    seconds: np.ndarray  # (N,) detector time per frame (backbone included)
    keyframes_judged: int = 0  # frames whose winner the decision measured (LoopDetector.keyframes_judged)
    too_short_to_decide: str | None = None  # why none was (LoopDetector.too_short_to_decide)


def recording_every_winner(config: SlamConfig) -> SlamConfig:
    """The same detector, but every keyframe's winner comes back as a proposal (for the PR curve):
    only the level below which nothing is *proposed* changes, never what is accepted."""
    out = config.model_copy(deep=True)
    detector = out.detector
    detector.calibrated = detector.calibrated.model_copy(update={"propose": float("-inf")})
    detector.min_score = 0.0
    detector.rear.min_score = 0.0
    return out


def path_positions(n: int, spacing: float) -> np.ndarray:
    """(n, 3) positions `spacing` metres apart along one line: only the distance travelled matters
    (the exclusion window), and two passes streamed as one traverse keep adding to it."""
    return np.c_[np.arange(n, dtype=np.float64) * spacing, np.zeros((n, 2))]


def travelled(positions: np.ndarray) -> np.ndarray:
    """Path length from the first position to each (metres)."""
    steps = np.linalg.norm(np.diff(np.asarray(positions, np.float64), axis=0), axis=1)
    return np.r_[0.0, np.cumsum(steps)]


ImagePair = tuple[np.ndarray, "np.ndarray | None"]
"""A keyframe's forward image and its rear image (None without a rear camera)."""


def images_of(files: Sequence[Path], rear: Sequence[Path] | None = None) -> Iterator[ImagePair]:
    """A folder pass read image by image (never all in memory)."""
    for k, path in enumerate(files):
        yield read_image(path), (read_image(rear[k]) if rear is not None else None)


def stream(
    config: SlamConfig,
    backbone: Backbone,
    passes: Sequence[Iterable[ImagePair]],
    positions: np.ndarray,
    on_frame: Callable[[], None] | None = None,
) -> StreamOutcome:
    """Stream the passes one after the other as one traverse; between passes the detector is told
    the path broke (`LoopDetector.break_sequence`): the second does not continue the first."""
    detector = build_detector(recording_every_winner(config), backbone)
    proposals: list[LoopProposal | None] = []
    seconds: list[float] = []
    frame = 0
    for p, images in enumerate(passes):
        if p:
            detector.break_sequence()
        pairs = iter(images)
        while True:
            start = time.perf_counter()
            pair = next(pairs, None)  # reading the image is part of the frame's time
            if pair is None:
                break
            image, rear_image = pair
            proposals.append(detector.process(image, frame, positions[frame], float(frame), rear_image))
            seconds.append(time.perf_counter() - start)
            frame += 1
            if on_frame is not None:
                on_frame()
    return StreamOutcome(tuple(proposals), np.array(seconds), detector.keyframes_judged,
                         detector.too_short_to_decide())  # fmt: skip
