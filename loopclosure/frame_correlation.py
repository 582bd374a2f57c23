"""The RAS 2020 frame-correlation prior for sequential query streams.

Consecutive queries come from consecutive places, so if query t-h matched reference m, query
t probably matches near m + h. Those places are boosted rather than forced: a strong spatial
match elsewhere still wins.

The failure of the prior as released: once a wrong place is recognised, its neighbours are
boosted, a boosted neighbour wins the next query, and the wrong lock feeds itself (measured on
Corridor with its queries cut into 6 shuffled segments: PR-AUC 0.780 without the prior, 0.284
with it). With `recover` (the default here), only a recognition that would have won without the
boost boosts later queries, so a lock must be renewed by evidence and a wrong one dies after
`history` queries (same stream: 0.798). The prior assumes both traversals run the same way; on
a reversed traverse it still hurts (Corridor reversed: 0.780 plain, 0.032 as released, 0.48
with recovery), hence it stays off by default.
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

    def update(self, match: int | None, supported: bool = True) -> None:
        """Record the query's recognition. supported: it would have won without the boost
        (with `recover`, an unsupported one is recorded as nothing recognised)."""
        self._history.append(match if supported or not self.config.recover else None)

    def reset(self) -> None:
        self._history.clear()
