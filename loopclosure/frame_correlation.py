"""The RAS 2020 frame-correlation prior for sequential query streams.

Consecutive queries come from consecutive places, so if query t-h matched reference m, query
t probably matches near m + h. Those places are boosted rather than forced: a strong spatial
match elsewhere still wins.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from loopclosure.config import FrameCorrelationConfig


class FrameCorrelationPrior:
    def __init__(self, config: FrameCorrelationConfig) -> None:
        self.config = config
        self._history: deque[int | None] = deque(maxlen=config.history)

    def boosted(self) -> np.ndarray:
        """Places to boost for the next query (empty until something was recognised)."""
        if not self.config.enabled:
            return np.empty(0, np.int64)
        radius = np.arange(-self.config.radius, self.config.radius + 1)
        centres = [m + h for h, m in enumerate(reversed(self._history), start=1) if m is not None]
        if not centres:
            return np.empty(0, np.int64)
        return np.unique(np.concatenate([c + radius for c in centres]))

    def update(self, match: int | None) -> None:
        self._history.append(match)

    def reset(self) -> None:
        self._history.clear()
