"""Whether earlier loops of a revisit vouch for a loop that no geometry verified.

Why: without a scan, and where two views of a place give no epipolar geometry (across day and
night they rarely do: Gardens Point's right day/night pairs gave 0-19 SIFT + MAGSAC inliers,
its wrong ones 0-11), nothing checks a camera loop but the recogniser itself. Pairwise
consistency with odometry (PCM, as Kimera-RPGO checks loops before they enter the graph) does:
two loops q_j -> m_j and q -> m of one revisit close a cycle with the odometry along both
visits, q_j -> q and m_j -> m; where one street was driven twice the cycle closes, where a
single keyframe matched the wrong place it does not. The check reads only loops already recorded,
so a resumed run decides as the uninterrupted one did.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ssmvpr_slam.backend.config import LoopConsistencyConfig
from ssmvpr_slam.backend.loop_registration import carry_loop
from ssmvpr_slam.backend.se3 import invert


@dataclass(frozen=True)
class LoopPose:
    """A loop's two ends in odometry and its relative pose T_mq (a place prior or a registration)."""

    query_id: int
    match_id: int
    query_pose: np.ndarray  # 4x4 odometry pose of the query keyframe
    match_pose: np.ndarray  # 4x4 pose of the matched keyframe (odometry; map pose for a prior-map place)
    T_mq: np.ndarray
    travelled_query: float  # path driven to the query keyframe (metres)
    travelled_match: float  # path driven to the matched keyframe (metres; prior-map places: NaN)


def disagreement(earlier: LoopPose, loop: LoopPose) -> tuple[float, float]:
    """(metres, degrees) between `loop`'s T_mq and `earlier`'s carried to the same two keyframes."""
    carried = carry_loop(earlier.T_mq, earlier.match_pose, earlier.query_pose, loop.match_pose, loop.query_pose)
    residual = invert(loop.T_mq) @ carried
    cos = (float(np.trace(residual[:3, :3])) - 1.0) / 2.0
    return float(np.linalg.norm(residual[:3, 3])), math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def allowed_m(config: LoopConsistencyConfig, path_m: float) -> float:
    """Metres two loops of one revisit may disagree by, `path_m` driven on the two stretches
    between them (odometry drifts along them)."""
    return config.max_translation_m + config.per_m_travelled * path_m


def in_window(config: LoopConsistencyConfig, query: int, match: int, earlier_query: int, earlier_match: int) -> bool:
    """Whether loop earlier_query -> earlier_match may vouch for query -> match: before it, and
    within `window_keyframes` of it on both visits (the same revisit)."""
    window = config.window_keyframes
    return 0 < query - earlier_query <= window and abs(match - earlier_match) <= window


def agrees(earlier: LoopPose, loop: LoopPose, config: LoopConsistencyConfig) -> bool:
    path = abs(loop.travelled_query - earlier.travelled_query)
    if math.isfinite(loop.travelled_match) and math.isfinite(earlier.travelled_match):
        path += abs(loop.travelled_match - earlier.travelled_match)
    metres, degrees = disagreement(earlier, loop)
    return metres <= allowed_m(config, path) and degrees <= config.max_rotation_deg


def support(loop: LoopPose, earlier: Iterable[LoopPose], config: LoopConsistencyConfig) -> int:
    """How many `earlier` loops of the same revisit (query at most `window_keyframes` before,
    match within as many of this match) agree with `loop`."""
    return sum(
        1
        for e in earlier
        if in_window(config, loop.query_id, loop.match_id, e.query_id, e.match_id) and agrees(e, loop, config)
    )
