"""Keyframe selection by distance, angle and time."""

from __future__ import annotations

import numpy as np
import pytest

from frontend.config import KeyframeConfig
from frontend.keyframes import KeyframeSelector
from frontend.odometry.logged import so3_exp


def _pose(x: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = so3_exp([0, 0, np.radians(yaw_deg)])
    pose[0, 3] = x
    return pose


def test_first_frame_is_always_a_keyframe() -> None:
    selector = KeyframeSelector(KeyframeConfig(min_distance_m=None, min_angle_deg=None))
    assert selector.select(_pose(), 0.0)
    assert not any(selector.select(_pose(x), x) for x in range(1, 50))  # everything off


def test_distance_threshold_measured_from_last_keyframe() -> None:
    selector = KeyframeSelector(KeyframeConfig(min_distance_m=1.0, min_angle_deg=None))
    picks = [selector.select(_pose(0.3 * k), 0.1 * k) for k in range(13)]
    # keyframes at x = 0, 1.2, 2.4, 3.6: each the first frame >= 1 m past the previous one
    assert picks == [True, False, False, False, True, False, False, False, True, False, False, False, True]
    assert selector.count == 4


def test_angle_threshold() -> None:
    selector = KeyframeSelector(KeyframeConfig(min_distance_m=None, min_angle_deg=10.0))
    picks = [selector.select(_pose(yaw_deg=4.0 * k), k) for k in range(6)]
    assert picks == [True, False, False, True, False, False]
    decision = selector.decide(_pose(yaw_deg=-6.0), 6.0)  # 18 degrees back from 12
    assert decision.is_keyframe and decision.angle_deg == pytest.approx(18.0)


def test_time_threshold() -> None:
    selector = KeyframeSelector(KeyframeConfig(min_distance_m=None, min_angle_deg=None, max_interval_s=2.0))
    picks = [selector.select(_pose(), t) for t in [0.0, 1.0, 1.9, 2.0, 3.5, 4.1]]
    assert picks == [True, False, False, True, False, True]
    selector.reset()
    assert selector.select(_pose(), 4.2) and selector.count == 1


def test_thresholds_must_be_positive() -> None:
    with pytest.raises(ValueError):
        KeyframeConfig(min_distance_m=0.0)
