"""Image sequences through the detector `run` builds, one keyframe per image."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from loopclosure.backbone import Backbone
from loopclosure.detector import LoopProposal
from loopclosure.images import read_image
from ssmvpr_slam.config import SlamConfig
from ssmvpr_slam.system import build_detector


@dataclass(frozen=True)
class StreamOutcome:
    proposals: tuple[LoopProposal | None, ...]  # per stream frame: its best sequence and the decision
    seconds: np.ndarray  # (N,) detector time per frame (backbone included)


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


def stream(
    config: SlamConfig,
    backbone: Backbone,
    passes: Sequence[Sequence[Path]],
    positions: np.ndarray,
    rear: Sequence[Sequence[Path]] | None = None,
    on_frame: Callable[[], None] | None = None,
) -> StreamOutcome:
    """Stream the passes one after the other as one traverse; between passes the detector is told
    the path broke (`LoopDetector.break_sequence`): the second does not continue the first."""
    detector = build_detector(recording_every_winner(config), backbone)
    proposals: list[LoopProposal | None] = []
    seconds: list[float] = []
    frame = 0
    for p, files in enumerate(passes):
        if p:
            detector.break_sequence()
        for k, path in enumerate(files):
            start = time.perf_counter()
            image = read_image(path)
            rear_image = read_image(rear[p][k]) if rear is not None else None
            proposals.append(detector.process(image, frame, positions[frame], float(frame), rear_image))
            seconds.append(time.perf_counter() - start)
            frame += 1
            if on_frame is not None:
                on_frame()
    return StreamOutcome(tuple(proposals), np.array(seconds))
