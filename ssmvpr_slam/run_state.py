"""What a run accumulates while frames stream in (`RunState`), the front half's own counters
(`FrontCounts`), and a keyframe as the front half hands it to the back half (`KeyframeInput`):
plain records the core, the pipeline and the progress display share."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from ssmvpr_slam.run_result import Keyframe, LoopRecord, StageTimes


@dataclass
class RunState:
    """What the system has accumulated so far (read it for progress; change it never).

    frames_seen / frames_skipped count the frames whose effects are in the state: with the
    stages overlapped the front end may be a few keyframes ahead, and a checkpoint must not
    count frames whose keyframes it does not hold."""

    keyframes: list[Keyframe] = field(default_factory=list)
    loops: list[LoopRecord] = field(default_factory=list)
    frames_seen: int = 0
    frames_skipped: Counter[str] = field(default_factory=Counter)
    rear_keyframes: int = 0  # keyframes queried with a rear image too
    times: StageTimes = field(default_factory=StageTimes)
    recognition_skipped: list[int] = field(default_factory=list)  # keyframes a live run handled by odometry alone


@dataclass
class FrontCounts:
    """The front half's own counters (frames read, skipped, keyframes selected)."""

    frames_seen: int = 0
    frames_skipped: Counter[str] = field(default_factory=Counter)
    keyframes: int = 0
    seconds: float = 0.0  # front-end time since the last keyframe (odometry, selection, keeping)


@dataclass(frozen=True)
class KeyframeInput:
    """A keyframe as the front half hands it to the back half: what the run keeps of it, the
    full images the detector encodes once (dropped after that), and the front's counts up to
    and including its frame."""

    keyframe: Keyframe
    image: np.ndarray
    rear_image: np.ndarray | None
    frames_seen: int
    frames_skipped: dict[str, int]
    front_seconds: float
