"""`loop-eval --verify`: every accepted loop checked by two views, as a run checks a camera loop.

The verifier is the one `run` uses (`backend.registration.two_view.deep`, on the detector's own
backbone). loop-eval only asks whether the two images can be views of one rigid scene, so it
fits the fundamental matrix and needs no intrinsics: image folders carry none. The passes are
read a second time and only the images of accepted loops are kept (at the verifier's width),
so a long sequence is never held in memory.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from loopclosure.backbone import Backbone
from loopclosure.dense_matches import DenseFeatures
from loopclosure.pair_verifier import PairVerdict, PairVerifier
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.loop_eval.stream import ImagePair, StreamOutcome

RECENT_FEATURES = 16
"""Dense features kept for reuse (about 2 MB each at 480 px wide)."""


@dataclass(frozen=True)
class Verification:
    """The verdict on each accepted loop (by its query's stream frame) and the seconds each took
    (both images' features and the geometry)."""

    verdicts: dict[int, PairVerdict]
    seconds: tuple[float, ...]

    def verified(self, n_frames: int) -> np.ndarray:
        """(n_frames,) bool: the frame's accepted loop verified."""
        out = np.zeros(n_frames, bool)
        for frame, verdict in self.verdicts.items():
            out[frame] = verdict.accepted
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
    config: SlamConfig,
    backbone: Backbone,
    on_loop: Callable[[], None] | None = None,
) -> Verification:
    """Verify the accepted loops of `outcome`; `passes` read the stream's images again."""
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
    return Verification(verdicts, tuple(seconds))
