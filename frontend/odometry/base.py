"""The odometry protocol and its counters."""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from frontend.frame import Frame

log = logging.getLogger("frontend.odometry")


@dataclass
class OdometryStats:
    """How many frames were processed and how many could not be (by reason)."""

    updates: int = 0
    skipped: Counter[str] = field(default_factory=Counter)  # frames whose pose was predicted
    notes: Counter[str] = field(default_factory=Counter)  # degraded but processed frames
    warned: set[str] = field(default_factory=set)

    def skip(self, reason: str, detail: str) -> None:
        """Count a frame whose data could not be used; log only the first of each reason."""
        self.skipped[reason] += 1
        self._warn_once(reason, detail)

    def note(self, reason: str, detail: str) -> None:
        """Count a frame that was processed in a degraded way (e.g. without deskewing)."""
        self.notes[reason] += 1
        self._warn_once(reason, detail)

    def _warn_once(self, reason: str, detail: str) -> None:
        if reason not in self.warned:
            self.warned.add(reason)
            log.warning("%s (further '%s' cases are only counted)", detail, reason)


@runtime_checkable
class Odometry(Protocol):
    """Turns a stream of Frames into poses: ``update(frame)`` returns the 4x4 pose of the
    frame's body in the odometry world frame. Bad sensor data never raises; it is counted
    in ``stats`` and the pose is predicted or held."""

    stats: OdometryStats

    def update(self, frame: Frame) -> np.ndarray: ...
