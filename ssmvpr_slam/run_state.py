"""What a run accumulates while frames stream in (`RunState`), the front half's own counters
(`FrontCounts`), and a keyframe as the front half hands it to the back half (`KeyframeInput`):
plain records the core, the pipeline and the progress display share."""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from loopclosure.detector import EncodedKeyframe
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


FRONT_PARTS = ("odometry", "odometry_wait", "keyframe_keeping")
"""Where the front end's time goes, as the back end's timing rows record it: the odometry's own
update (in its process where it has one), the front end's wait for the pose (one frame at a time,
that update and the frame's way there and back; with frames handed ahead, what is left of the
update when the front end asks), and keeping the keyframe (its scan, reduced images,
thumbnail). What front_end has beyond the wait and the keeping is selection and checks. With
frames handed ahead the odometry's update overlaps the rest, so the parts need not add up to
less than front_end."""


@dataclass
class FrontCounts:
    """The front half's own counters (frames read, skipped, keyframes selected)."""

    frames_seen: int = 0
    frames_skipped: Counter[str] = field(default_factory=Counter)
    keyframes: int = 0
    seconds: float = 0.0  # front-end time since the last keyframe (odometry, selection, keeping)
    parts: defaultdict[str, float] = field(default_factory=lambda: defaultdict(float))  # by part (FRONT_PARTS)

    def odometry_done(self, waited: float, odometry: object) -> None:
        """The front end waited `waited` s for a pose; the odometry's own time is its `last_update_s`
        where it runs in a process of its own, else the wait."""
        own = getattr(odometry, "last_update_s", None)
        self.parts["odometry"] += waited if own is None else own
        self.parts["odometry_wait"] += waited

    def take_parts(self) -> dict[str, float]:
        """The seconds by part since the last keyframe, counted afresh from here."""
        parts = {name: self.parts[name] for name in FRONT_PARTS}
        self.parts.clear()
        return parts


@dataclass(frozen=True)
class KeyframeInput:
    """A keyframe as the front half hands it to the back half: what the run keeps of it, the
    full images the detector encodes once (dropped after that), the front's counts up to and
    including its frame, and its codes where they were encoded ahead (`pipeline.encode_ahead`)."""

    keyframe: Keyframe
    image: np.ndarray
    rear_image: np.ndarray | None
    frames_seen: int
    frames_skipped: dict[str, int]
    front_seconds: float
    front_parts: Mapping[str, float] = field(default_factory=dict)  # FRONT_PARTS: where front_seconds went
    encoded: EncodedKeyframe | None = None
    back_end_wait: float = 0.0  # seconds the back end waited for it (stages overlapped: its idle time)
