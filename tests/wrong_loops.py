"""A test double of the pose graph that adds deliberately wrong loop factors.

The robustness tests ask whether wrong loops, as confident as real ICP loops, move the
optimised trajectory. Production code has no such option: the double is handed to
`SlamSystem(..., graph=WrongLoopGraph(...))`. Before each iSAM2 step of a keyframe at or after
`first_keyframe` it adds, with probability `rate`, a loop from that keyframe to a random
earlier one with an identity relative pose. The system never sees these loops: they are not
proposals, so loop metrics and loop_closures.csv describe the recogniser alone, while the
trajectory carries their effect.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ssmvpr_slam.backend.config import PoseGraphConfig
from ssmvpr_slam.backend.pose_graph import PoseGraph


@dataclass(frozen=True)
class InjectedLoop:
    handle: int
    query: int  # the keyframe the loop was added at
    match: int  # the random earlier keyframe it claims to revisit


class WrongLoopGraph(PoseGraph):
    def __init__(
        self, config: PoseGraphConfig, rate: float, sigmas: np.ndarray, first_keyframe: int = 2, seed: int = 0
    ) -> None:
        super().__init__(config)
        self.rate = rate
        self.sigmas = np.asarray(sigmas, np.float64)
        self.first_keyframe = max(first_keyframe, 2)
        self.injected: list[InjectedLoop] = []
        self._rng = np.random.default_rng(seed)
        self._last_considered = -1

    def update(self) -> None:
        ids = self.keyframe_ids
        if ids and ids[-1] != self._last_considered:
            self._last_considered = kf = ids[-1]
            if kf >= self.first_keyframe and self._rng.random() < self.rate:
                wrong = int(self._rng.integers(0, kf - 1))
                handle = self.add_loop(wrong, kf, np.eye(4), sigmas=self.sigmas)
                self.injected.append(InjectedLoop(handle, kf, wrong))
        super().update()
