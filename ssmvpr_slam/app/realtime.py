"""Playing a log as its sensor recorded it: frames at their recorded rate, and a run that falls
behind catching up by leaving recognition out, said and counted.

Why: a streaming plugin must keep pace with the stream it is fed, and a logged run hides
whether it does. `run --realtime` gives frame i to the system no earlier than
start + (t_i - t_0) / rate (t: the frame's timestamp). A keyframe that reaches the back end more
than `pipeline.realtime_max_lag_s` after its frame was due is handled by odometry alone (no
backbone, no proposal, no place): the run catches up instead of falling further behind, and
every such keyframe is counted. RTAB-Map bounds the time of each update for the same reason.
The lag of a keyframe is from its frame's due time to the end of its back-end step.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from frontend.frame import Frame
from ssmvpr_slam.run_result import RealtimeStats


class SensorClock:
    """The recorded timeline of a log, replayed at `rate` times its speed."""

    def __init__(
        self,
        rate: float,
        max_lag_s: float,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"real-time rate must be a positive number, got {rate}")
        if not (math.isfinite(max_lag_s) and max_lag_s >= 0):
            raise ValueError(f"real-time lag bound must be 0 or more seconds, got {max_lag_s}")
        self.rate, self.max_lag_s = rate, max_lag_s
        self._clock, self._sleep = clock, sleep
        self._origin: tuple[float, float] | None = None  # (first frame's timestamp, the wall time it was due)
        self._due: dict[int, float] = {}  # frame index -> when it was due, until its keyframe is done
        self._due_lock = threading.Lock()  # the source's thread adds frames while the back end's takes them
        self._last_due = -math.inf
        self._lags: list[float] = []
        self._skipped = 0

    def paced(self, frames: Iterable[Frame]) -> Iterator[Frame]:
        """The frames, each no earlier than its recorded time (a frame without a usable timestamp,
        or one earlier than the frame before it, is due with the frame before it)."""
        for frame in frames:
            due = self._due_time(frame.timestamp)
            wait = due - self._clock()
            if wait > 0:
                self._sleep(wait)
            with self._due_lock:
                self._due[frame.index] = due
            yield frame

    def _due_time(self, stamp: float) -> float:
        if self._origin is None:
            if not math.isfinite(stamp):
                stamp = 0.0
            self._origin = (stamp, self._clock())
        first, start = self._origin
        due = start + (stamp - first) / self.rate if math.isfinite(stamp) else self._last_due
        self._last_due = max(self._last_due, due)
        return self._last_due

    def behind(self, frame_index: int) -> bool:
        """Whether a keyframe of this frame is later than the bound: it skips recognition."""
        with self._due_lock:
            due = self._due.get(frame_index)
        return due is not None and self._clock() - due > self.max_lag_s

    def done(self, frame_index: int, skipped: bool) -> None:
        """A keyframe of this frame left the back end (skipped: without recognition)."""
        with self._due_lock:
            due = self._due.pop(frame_index, None)
            for index in [i for i in self._due if i < frame_index]:  # frames that were no keyframe
                del self._due[index]
        if due is not None:
            self._lags.append(self._clock() - due)
        self._skipped += skipped

    def stats(self) -> RealtimeStats:
        lags = np.asarray(self._lags, np.float64)
        have = len(lags) > 0
        return RealtimeStats(
            self.rate, self.max_lag_s, len(lags), self._skipped,
            float(np.median(lags)) if have else None, float(np.percentile(lags, 99)) if have else None,
            float(lags.max()) if have else None,
        )  # fmt: skip
