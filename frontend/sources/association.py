"""Streaming nearest-timestamp association with bounded buffers.

One stream drives (each of its messages becomes a frame); every other stream contributes
the message nearest in time to the frame, if within ``tolerance``. Messages arrive merged
in log order, each stream strictly increasing in time. A pending frame at time t is
decided for a stream as soon as that stream has a message at or after t (later messages
can only be further away), or once the newest time seen anywhere passes
t + tolerance + max_latency (the stream is late or silent). Buffers stay bounded: pending
frames are capped; a full look-back buffer is first thinned to the messages that can still
be nearest to a pending or future frame, and only then forces the oldest pending frame out.
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from frontend.sources.base import SourceStats


@dataclass
class Associated:
    """A decided frame: driving payload plus the matched payload of each other stream."""

    time: float
    payload: Any
    matches: dict[str, Any] = field(default_factory=dict)


class StreamAssociator:
    """Nearest-in-time matching of auxiliary streams to a driving stream, online."""

    def __init__(
        self,
        aux_roles: list[str],
        tolerance: float,
        max_latency: float,
        max_pending: int,
        max_buffered: int,
        stats: SourceStats,
    ) -> None:
        self.tolerance = tolerance
        self.max_latency = max_latency
        self.max_pending = max_pending
        self.max_buffered = max_buffered
        self.stats = stats
        self._pending: deque[tuple[float, Any]] = deque()
        self._buffers: dict[str, deque[tuple[float, Any]]] = {r: deque() for r in aux_roles}
        self._newest: dict[str, float] = {}
        self._clock = float("-inf")
        self._last_driver = float("-inf")

    def add_driver(self, time: float, payload: Any) -> list[Associated]:
        self._pending.append((time, payload))
        self._last_driver = time
        self._clock = max(self._clock, time)
        return self._drain()

    def add_aux(self, role: str, time: float, payload: Any) -> list[Associated]:
        ready: list[Associated] = []
        buffer = self._buffers[role]
        if len(buffer) >= self.max_buffered:
            self._thin(buffer)
        while len(buffer) >= self.max_buffered and self._pending:
            self.stats.notes["association_forced"] += 1
            ready.append(self._decide())
        if len(buffer) >= self.max_buffered:
            buffer.popleft()
        buffer.append((time, payload))
        self._newest[role] = time
        self._clock = max(self._clock, time)
        return ready + self._drain()

    def flush(self) -> list[Associated]:
        """Decide every pending frame with what has arrived (end of log)."""
        return [self._decide() for _ in range(len(self._pending))]

    def _thin(self, buffer: deque[tuple[float, Any]]) -> None:
        """Keep only messages that can still be the nearest one to some frame: around each
        pending frame, the last one at or before the newest driving time, and all after it."""
        times = [item[0] for item in buffer]
        keep = set(range(bisect_right(times, self._last_driver), len(times)))
        for anchor in [t for t, _ in self._pending] + [self._last_driver]:
            before, after = bisect_right(times, anchor) - 1, bisect_left(times, anchor)
            keep.update(i for i in (before, after) if 0 <= i < len(times))
        kept = [item for i, item in enumerate(buffer) if i in keep]
        buffer.clear()
        buffer.extend(kept)

    def _ready(self, time: float) -> bool:
        if self._clock >= time + self.tolerance + self.max_latency:
            return True
        return all(self._newest.get(role, float("-inf")) >= time for role in self._buffers)

    def _drain(self) -> list[Associated]:
        ready = []
        while self._pending and (len(self._pending) > self.max_pending or self._ready(self._pending[0][0])):
            ready.append(self._decide())
        return ready

    def _decide(self) -> Associated:
        time, payload = self._pending.popleft()
        result = Associated(time, payload)
        for role, buffer in self._buffers.items():
            best = min(buffer, key=lambda item: abs(item[0] - time), default=None)
            if best is not None and abs(best[0] - time) <= self.tolerance:
                result.matches[role] = best[1]
            else:
                self.stats.notes[f"unmatched_{role}"] += 1
            # Later frames are later in time: messages older than t - tolerance are useless.
            while buffer and buffer[0][0] < time - self.tolerance:
                buffer.popleft()
        return result
