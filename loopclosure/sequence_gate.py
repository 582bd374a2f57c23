"""The sequence prior as a gate (the paper's future work, made a filter).

A single frame can look like many places; a run of consecutive frames that all match a run
of consecutive places almost never does by accident. A closure i -> j is accepted only when
the recognitions of keyframes i-1 .. i-(L-1) lie within ±tol of j-1 .. j-(L-1) (a revisit
driven the same way) or of j+1 .. j+(L-1) (driven the opposite way).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

from loopclosure.config import SequenceGateConfig
from loopclosure.saved_state import saved_ints


@dataclass(frozen=True)
class GateDecision:
    accepted: bool
    reason: str
    direction: Literal["forward", "reverse"] | None = None


class SequenceGate:
    def __init__(self, config: SequenceGateConfig) -> None:
        self.config = config
        self._recent: deque[tuple[int, int | None]] = deque(maxlen=max(config.length - 1, 1))

    def observe(self, query: int, match: int | None) -> None:
        """Record keyframe `query`'s recognition (None when it recognised nothing)."""
        self._recent.append((query, match))

    def decide(self, query: int, match: int) -> GateDecision:
        """Judge query -> match against the recognitions observed so far (call before `observe`)."""
        need = self.config.length - 1
        if need == 0:
            return GateDecision(True, "accepted: gate length 1", "forward")
        history = {q: m for q, m in self._recent}
        predecessors = [history.get(query - k) for k in range(1, need + 1)]
        missing = [k for k, m in enumerate(predecessors, start=1) if m is None]
        if missing:
            k = missing[0]
            what = "not seen" if (query - k) not in history else "recognised nothing"
            return GateDecision(False, f"keyframe {query - k} {what}")
        matched = [m for m in predecessors if m is not None]  # all of them, after the check above
        tol = self.config.tolerance
        for direction, sign in (("forward", -1), ("reverse", +1)):
            if direction == "reverse" and not self.config.allow_reverse:
                continue
            if all(abs(m - (match + sign * k)) <= tol for k, m in enumerate(matched, start=1)):
                return GateDecision(True, f"accepted: {need} predecessors consistent ({direction})", direction)  # type: ignore[arg-type]
        k, m = next((k, m) for k, m in enumerate(matched, start=1) if abs(m - (match - k)) > tol)
        return GateDecision(
            False,
            f"keyframe {query - k} matched {m}, expected {match - k}±{tol}"
            + (f" or {match + k}±{tol}" if self.config.allow_reverse else ""),
        )

    def reset(self) -> None:
        self._recent.clear()

    def state_arrays(self) -> dict[str, np.ndarray]:
        """The recent recognitions as arrays (-1: recognised nothing), for checkpoints."""
        recent = list(self._recent)
        return {
            "gate_queries": np.array([q for q, _ in recent], np.int64),
            "gate_matches": np.array([-1 if m is None else m for _, m in recent], np.int64),
        }

    @staticmethod
    def check_state_arrays(arrays: dict[str, np.ndarray], n_places: int) -> None:
        """Refuse saved matches outside a map of `n_places` (-1 is "recognised nothing")."""
        if "gate_matches" in arrays:
            saved_ints(arrays, "gate_matches", -1, n_places)

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        self.reset()
        for query, match in zip(arrays["gate_queries"].tolist(), arrays["gate_matches"].tolist()):
            self._recent.append((query, None if match < 0 else match))
