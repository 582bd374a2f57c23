"""One clock policy for every reader: a stream's time must go forward, and big leaps are told.

A message whose time is not after the previous one of its stream is skipped and counted: it
is either a duplicate or a clock that jumped back, and taking it would interleave two parts
of the traverse. A leap forward of more than ``max_gap_s`` is kept (the recording paused, or
the clock was set forward) but counted and warned about once, because odometry across a gap
that long is a guess.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from frontend.errors import FrontendInputError
from frontend.sources.base import SourceStats
from ssmvpr_common.quoting import shortened
from ssmvpr_common.text_files import read_text

DEFAULT_MAX_GAP_S = 5.0
MAX_TIME_S = float(2**31 - 1)
"""The last second a ROS time can hold (int32 seconds, January 2038): a later time could be read
but never written back (the trajectory log, a converted bag), so it is refused before any work."""


def time_problem(time: float) -> str | None:
    """Why `time` (seconds) cannot be a frame's time, or None."""
    if not math.isfinite(time):
        return f"time {time} is not finite"
    if not 0.0 <= time <= MAX_TIME_S:
        return f"time {time:.9g} s is outside 0 .. {MAX_TIME_S:.0f} s (what a ROS time can hold, until 2038)"
    return None


def read_times(path: Path) -> np.ndarray:
    """A times file (one time in seconds per line), refused with one line naming the file when it
    is not text, not numbers, not finite, or holds a time no writer could keep."""
    text = read_text(path, FrontendInputError)
    try:
        times = np.loadtxt(text.splitlines(), dtype=np.float64, ndmin=1)
    except ValueError as error:
        raise FrontendInputError(f"{path}: unreadable ({shortened(str(error))})") from None
    if times.ndim != 1 or not np.all(np.isfinite(times)):
        raise FrontendInputError(f"{path}: need one finite time per line")
    for line, time in enumerate(times.tolist(), start=1):
        problem = time_problem(time)
        if problem is not None:
            raise FrontendInputError(f"{path} line {line}: {problem}; refusing the times")
    return times


class StreamClock:
    """Per-stream last time, checked with :meth:`accept` as each message arrives."""

    def __init__(self, stats: SourceStats, max_gap_s: float = DEFAULT_MAX_GAP_S) -> None:
        self.stats = stats
        self.max_gap_s = max_gap_s
        self._last: dict[str, float] = {}

    def accept(self, stream: str, time: float, where: str) -> bool:
        """True to use the message; False (counted, first one warned) to skip it."""
        problem = time_problem(time)
        if problem is not None:
            self.stats.skip(f"bad_time_{stream}", f"{where}: {problem}; skipped")
            return False
        last = self._last.get(stream)
        if last is not None and time <= last:
            self.stats.skip(
                f"non_monotonic_{stream}",
                f"{where}: {stream} time {time:.9f} is not after {last:.9f} (duplicate, or the "
                "clock went back); skipped until the time passes it again",
            )
            return False
        if last is not None and time - last > self.max_gap_s:
            self.stats.warn(
                f"clock_jump_{stream}",
                f"{where}: {stream} time leaps {time - last:.3f} s forward (> {self.max_gap_s} s); "
                "kept, but odometry across the gap is a guess",
            )
        self._last[stream] = time
        return True
