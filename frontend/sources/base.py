"""What every data source is: an iterable of Frames with counters and a description."""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from frontend.frame import Frame
from frontend.sources.intrinsics import CameraIntrinsics, k_problem
from frontend.sources.pose_jumps import PoseJumpCheck

log = logging.getLogger("frontend.sources")


@dataclass
class SourceStats:
    """Per-source counters: how many frames came out, and what was skipped and why."""

    frames_yielded: int = 0
    skipped: Counter[str] = field(default_factory=Counter)
    notes: Counter[str] = field(default_factory=Counter)  # e.g. unmatched_lidar
    warned: set[str] = field(default_factory=set)
    quiet: bool = False  # a read-ahead (choosing the clock) counts nothing that the real pass will tell

    def skip(self, reason: str, detail: str) -> None:
        """Count a skip; log the first of each reason (a long log must not flood the console)."""
        self.skipped[reason] += 1
        if reason not in self.warned and not self.quiet:
            self.warned.add(reason)
            log.warning("%s (further '%s' skips are only counted)", detail, reason)

    def warn(self, reason: str, detail: str) -> None:
        """Count something kept but doubtful (a note); log the first of each reason."""
        self.notes[reason] += 1
        if reason not in self.warned and not self.quiet:
            self.warned.add(reason)
            log.warning("%s (further '%s' cases are only counted)", detail, reason)

    def summary(self) -> str:
        """One line for logs and reports."""
        skips = ", ".join(f"{k}={v}" for k, v in sorted(self.skipped.items())) or "none"
        notes = ", ".join(f"{k}={v}" for k, v in sorted(self.notes.items()))
        return f"{self.frames_yielded} frames yielded; skipped: {skips}" + (f"; {notes}" if notes else "")


class Source(ABC):
    """A logged traverse, iterable over :class:`~frontend.frame.Frame` in time order.

    ``len()`` works when the number of frames is known up front (it raises TypeError
    otherwise; use :attr:`length` to ask without raising). ``topics`` maps each role
    (camera, lidar, logged_pose, gt_pose) to where it comes from; ``intrinsics`` gives each
    camera's calibration when the log carries one.
    """

    def __init__(self) -> None:
        self.stats = SourceStats()
        self._jumps: dict[str, PoseJumpCheck] = {}  # per pose role, afresh for each reading
        self._calibration_notes: Counter[str] = Counter()  # read once, counted in every reading's stats

    @abstractmethod
    def __iter__(self) -> Iterator[Frame]: ...

    def reset_stats(self) -> None:
        """Start counting afresh (each iteration re-reads the traverse from the start); what
        reading the calibration found stays counted, as it is not read again."""
        self.stats = SourceStats()
        self._jumps = {}
        self.stats.notes.update(self._calibration_notes)
        self.stats.warned.update(self._calibration_notes)

    @property
    def intrinsics(self) -> dict[str, CameraIntrinsics]:
        """Camera role (``camera``, ``rear_camera``) -> its pinhole calibration for its images at
        their native resolution; roles without a (valid) calibration in the log are left out."""
        return {}

    def calibration(self, values: object, width: int | None, height: int | None, where: str) -> CameraIntrinsics | None:
        """CameraIntrinsics of a K read from the log, or None (a counted warning) when it is
        unusable: a wrong K would misplace every pixel, a missing one only costs what needs it."""
        problem = k_problem(values)
        if problem is not None:
            self.calibration_warning("invalid_calibration", f"{where}: {problem}; calibration ignored")
            return None
        return CameraIntrinsics(np.asarray(values, dtype=np.float64), width or None, height or None)

    def calibration_warning(self, reason: str, detail: str) -> None:
        """A counted warning about the log's calibration, kept through `reset_stats`."""
        self._calibration_notes[reason] += 1
        self.stats.warn(reason, detail)

    def plausible_pose(self, role: str, pose: np.ndarray, time: float, where: str) -> np.ndarray | None:
        """The pose, or None (a counted skip) when it jumps further than a vehicle can move
        since the stream's last accepted pose (`frontend.sources.pose_jumps`): a glitch of a
        message or two must not pull a spike into the trajectory or break the pose graph."""
        verdict = self._jumps.setdefault(role, PoseJumpCheck()).check(time, pose)
        if verdict.refused is not None:
            self.stats.skip(f"implausible_{role}", f"{where}: {verdict.refused}; pose skipped")
            return None
        if verdict.relocated is not None:
            self.stats.warn(f"relocated_{role}", f"{where}: {verdict.relocated}")
        return pose

    @property
    def length(self) -> int | None:
        """Number of frames when known before reading, else None."""
        return None

    def __len__(self) -> int:
        if self.length is None:
            raise TypeError(f"{type(self).__name__}: number of frames is not known up front")
        return self.length

    @property
    @abstractmethod
    def topics(self) -> dict[str, str]:
        """Role -> topic / folder / file that feeds it (roles absent from the log are left out)."""

    @property
    @abstractmethod
    def description(self) -> str:
        """One human-readable line: what is being read."""
