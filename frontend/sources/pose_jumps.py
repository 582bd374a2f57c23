"""Refuse a logged pose that jumps further than any vehicle travels in the time since the last.

A pose stream (odometry, ground truth) that glitches for a message or two, to 1e4 m away and
back, is finite and a valid rigid transform, so nothing else stops it: its keyframe would pull a
spike into the trajectory, and at some 3e4 m the pose graph's solver loses precision (see
`ssmvpr_slam.backend.pose_graph`). Each pose is compared with the last one accepted on its
stream; a move faster than `MAX_SPEED_M_S` (plus `SLACK_M` for stamp jitter) is refused. The
check never locks a stream out: when `RELOCATION_MESSAGES` refused poses in a row, spanning
`RELOCATION_SECONDS` at least, agree with each other, the stream was moved on purpose (an odometry reset, a relocalisation) and is
followed from there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAX_SPEED_M_S = 1000.0  # ten times a fast car: only a glitch moves a pose this fast
SLACK_M = 10.0  # two messages with (nearly) the same stamp may still differ a little
RELOCATION_MESSAGES = 5  # a glitch lasts a message or two; five agreeing poses are a new track ...
RELOCATION_SECONDS = 1.0  # ... when they span a second too (at 100 Hz five messages are a 50 ms glitch)


@dataclass(frozen=True)
class _Fix:
    time: float
    position: np.ndarray


@dataclass(frozen=True)
class JumpVerdict:
    """What `PoseJumpCheck.check` made of a pose: refused (why), or accepted as a relocation."""

    refused: str | None = None
    relocated: str | None = None


class PoseJumpCheck:
    """One pose stream's last accepted pose and the run of poses refused since."""

    def __init__(self) -> None:
        self._accepted: _Fix | None = None
        self._refused: list[_Fix] = []

    def check(self, time: float, pose: np.ndarray) -> JumpVerdict:
        """Accept (the pose becomes the reference), or refuse with the speed it implies."""
        fix = _Fix(time, np.asarray(pose, dtype=np.float64)[:3, 3].copy())
        jump = None if self._accepted is None else _jump(self._accepted, fix)
        if jump is None:
            self._accept(fix)
            return JumpVerdict()
        if self._refused and _jump(self._refused[-1], fix) is not None:
            self._refused = []  # scattered glitches, not a track that moved
        self._refused.append(fix)
        span = self._refused[-1].time - self._refused[0].time
        if len(self._refused) < RELOCATION_MESSAGES or span < RELOCATION_SECONDS:
            return JumpVerdict(refused=jump)
        n = len(self._refused)
        self._accept(fix)
        return JumpVerdict(relocated=f"{jump}, but the last {n} poses agree: followed from here")

    def _accept(self, fix: _Fix) -> None:
        self._accepted = fix
        self._refused = []


def _jump(before: _Fix, after: _Fix) -> str | None:
    """Why moving from `before` to `after` is implausible, or None."""
    distance = math.dist(after.position, before.position)  # scaled: no overflow at 1e300 m
    seconds = abs(after.time - before.time)
    if distance <= MAX_SPEED_M_S * seconds + SLACK_M:
        return None
    return f"pose jumped {distance:.4g} m in {seconds:.3g} s since the last accepted one (over {MAX_SPEED_M_S:.0f} m/s)"
