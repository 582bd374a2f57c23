"""`loop-eval --verify`: every accepted loop checked by two views, as a run checks a camera loop.

The verifier is the one `run` uses (`backend.registration.two_view.deep`, on the detector's own
backbone). loop-eval only asks whether the two images can be views of one rigid scene, so it
fits the fundamental matrix and needs no intrinsics: image folders carry none. The passes are
read a second time and only the images of accepted loops are kept (at the verifier's width),
so a long sequence is never held in memory.

A loop the views refuse is treated as a run treats it (`two_view.on_geometry_failure`): with
`consistent`, it is kept when enough earlier loops of its revisit that the views *did* verify
agree with it along the path (`agreeing_loops`); a run checks that agreement under odometry,
loop-eval has only the distance travelled along the stream. Supporters must be verified ones:
the detector's own loops agree with each other by construction (its sequence matching), so
letting unverified ones vouch would keep a stretch of look-alikes the views refused.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from loopclosure.backbone import Backbone
from loopclosure.dense_matches import DenseFeatures
from loopclosure.pair_verifier import PairVerdict, PairVerifier
from ssmvpr_slam.backend.config import LoopConsistencyConfig
from ssmvpr_slam.backend.loop_consistency import allowed_m, in_window
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.loop_eval.stream import ImagePair, StreamOutcome, travelled

RECENT_FEATURES = 16
"""Dense features kept for reuse (about 2 MB each at 480 px wide)."""


@dataclass(frozen=True)
class Verification:
    """The verdict on each accepted loop (by its query's stream frame), the seconds each took
    (both images' features and the geometry), and the refused loops kept because earlier
    verified loops of their revisit agree with them (frame -> how many)."""

    verdicts: dict[int, PairVerdict]
    seconds: tuple[float, ...]
    agreed: dict[int, int] = field(default_factory=dict)

    def stands(self, frame: int) -> bool:
        """The frame's accepted loop stands: verified, too small to judge, or vouched for."""
        verdict = self.verdicts[frame]
        return verdict.accepted or not verdict.verifiable or frame in self.agreed

    def standing(self, n_frames: int) -> np.ndarray:
        """(n_frames,) bool: `stands`, per frame (False where no loop was checked)."""
        out = np.zeros(n_frames, bool)
        for frame in self.verdicts:
            out[frame] = self.stands(frame)
        return out

    def verified(self, n_frames: int) -> np.ndarray:
        """(n_frames,) bool: the frame's accepted loop verified."""
        out = np.zeros(n_frames, bool)
        for frame, verdict in self.verdicts.items():
            out[frame] = verdict.accepted
        return out

    def kept_by_agreement(self, n_frames: int) -> np.ndarray:
        """(n_frames,) bool: the frame's loop was refused by the views but earlier verified loops vouch for it."""
        out = np.zeros(n_frames, bool)
        out[list(self.agreed)] = True
        return out

    def unverifiable(self, n_frames: int) -> np.ndarray:
        """(n_frames,) bool: the frame's images were too small to judge (kept as the detector decided)."""
        out = np.zeros(n_frames, bool)
        for frame, verdict in self.verdicts.items():
            out[frame] = not verdict.verifiable
        return out


def _reduced(image: np.ndarray, width: int | None) -> np.ndarray:
    """The image at the verifier's width, as `dense_features` would make it: what is kept costs
    no more than the verifier reads."""
    if width is None or image.shape[1] <= width:
        return image
    height = max(1, int(round(image.shape[0] * width / image.shape[1])))
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def verify_accepted(
    outcome: StreamOutcome,
    passes: Sequence[Callable[[], Iterable[ImagePair]]],
    positions: np.ndarray,
    config: SlamConfig,
    backbone: Backbone,
    on_loop: Callable[[], None] | None = None,
) -> Verification:
    """Verify the accepted loops of `outcome`; `passes` read the stream's images again,
    `positions` (one a frame) give the distance travelled for the agreement rule."""
    verifier = PairVerifier(backbone, config.backend.registration.two_view.deep)
    loops = {q: p for q, p in enumerate(outcome.proposals) if p is not None and p.accepted}
    wanted: dict[tuple[int, str], None] = {}
    for q, p in loops.items():
        wanted[(q, "rear" if p.camera == "rear" else "front")] = None
        wanted[(p.match_id, "front")] = None
    kept: dict[tuple[int, str], np.ndarray] = {}
    frame = 0
    for read in passes:
        for front, rear in read():
            for camera, image in (("front", front), ("rear", rear)):
                if image is not None and (frame, camera) in wanted:
                    kept[(frame, camera)] = _reduced(image, verifier.config.width)
            frame += 1
    features: dict[tuple[int, str], DenseFeatures] = {}  # the latest few: a place matched again soon after

    def of(key: tuple[int, str]) -> DenseFeatures:
        if key not in features:
            if len(features) >= RECENT_FEATURES:
                features.pop(next(iter(features)))
            features[key] = verifier.features(kept[key], f"stream frame {key[0]} ({key[1]} camera)")
        return features[key]

    verdicts: dict[int, PairVerdict] = {}
    seconds: list[float] = []
    for q, p in loops.items():
        start = time.perf_counter()
        query_key = (q, "rear" if p.camera == "rear" else "front")
        verdicts[q] = verifier.verify(of(query_key), of((p.match_id, "front")))
        seconds.append(time.perf_counter() - start)
        if on_loop is not None:
            on_loop()
    agreed: dict[int, int] = {}
    if config.backend.registration.two_view.on_geometry_failure == "consistent":
        agreed = agreeing_loops(outcome, verdicts, travelled(positions), config.backend.registration.consistency)
    return Verification(verdicts, tuple(seconds), agreed)


def agreeing_loops(
    outcome: StreamOutcome, verdicts: dict[int, PairVerdict], path_m: np.ndarray, rule: LoopConsistencyConfig
) -> dict[int, int]:
    """The refused loops that at least `rule.min_support` earlier *verified* loops of the same
    revisit agree with, and how many do. Loops q_j -> m_j and q -> m agree, as in a run
    (`backend.loop_consistency`), when the two stretches of path between them match: the match
    moved as far as the query did (backwards for a reverse revisit), within
    `max_translation_m` plus `per_m_travelled` of both stretches; supporters lie at most
    `window_keyframes` before the query and from the match."""
    proposals = outcome.proposals
    verified = [q for q, v in verdicts.items() if v.accepted]
    out: dict[int, int] = {}
    for q, verdict in verdicts.items():
        if verdict.accepted or not verdict.verifiable:
            continue
        loop = proposals[q]
        assert loop is not None
        sign = -1.0 if loop.direction == "reverse" else 1.0
        support = 0
        for j in verified:
            earlier = proposals[j]
            assert earlier is not None
            if earlier.direction != loop.direction or not in_window(rule, q, loop.match_id, j, earlier.match_id):
                continue
            moved_query = path_m[q] - path_m[j]
            moved_match = path_m[loop.match_id] - path_m[earlier.match_id]
            support += abs(moved_match - sign * moved_query) <= allowed_m(rule, abs(moved_query) + abs(moved_match))
        if support >= rule.min_support:
            out[q] = support
    return out
