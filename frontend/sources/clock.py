"""One clock policy for every reader: a stream's time must go forward, and big leaps are told.

A message whose time is not after the previous one of its stream is skipped and counted: it
is either a duplicate or a clock that jumped back, and taking it would interleave two parts
of the traverse. A leap forward of more than ``max_gap_s`` is kept (the recording paused, or
the clock was set forward) but counted and warned about once, because odometry across a gap
that long is a guess.
"""

from __future__ import annotations

import math

from frontend.sources.base import SourceStats

DEFAULT_MAX_GAP_S = 5.0


class StreamClock:
    """Per-stream last time, checked with :meth:`accept` as each message arrives."""

    def __init__(self, stats: SourceStats, max_gap_s: float = DEFAULT_MAX_GAP_S) -> None:
        self.stats = stats
        self.max_gap_s = max_gap_s
        self._last: dict[str, float] = {}

    def accept(self, stream: str, time: float, where: str) -> bool:
        """True to use the message; False (counted, first one warned) to skip it."""
        if not math.isfinite(time):
            self.stats.skip(f"bad_time_{stream}", f"{where}: time {time} is not finite; skipped")
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
