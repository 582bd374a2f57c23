"""Keyframe selection: enough motion or enough time since the last keyframe.

Place recognition needs places, not frames: a robot standing still would otherwise flood
the database with one place. A frame becomes a keyframe when, relative to the last
keyframe, it has moved at least ``min_distance_m``, turned at least ``min_angle_deg`` or
``max_interval_s`` has passed (each criterion off when None). The first is always one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from frontend.config import KeyframeConfig


def rotation_angle(rotation: np.ndarray) -> float:
    """Angle (rad) of a rotation matrix."""
    cos = (np.trace(rotation) - 1.0) / 2.0
    return float(np.arccos(np.clip(cos, -1.0, 1.0)))


@dataclass
class KeyframeDecision:
    """Why a frame was (or was not) selected: handy for logs and plots."""

    is_keyframe: bool
    distance_m: float
    angle_deg: float
    interval_s: float


class KeyframeSelector:
    """``select(pose, timestamp)`` -> True when the frame should be a keyframe."""

    def __init__(self, config: KeyframeConfig | None = None) -> None:
        self.config = config or KeyframeConfig()
        self._last_pose: np.ndarray | None = None
        self._last_time = 0.0
        self.count = 0

    def reset(self) -> None:
        self._last_pose = None
        self.count = 0

    def decide(self, pose: np.ndarray, timestamp: float) -> KeyframeDecision:
        """Decide for one frame (and remember it when it is a keyframe)."""
        pose = np.asarray(pose, dtype=np.float64)
        if self._last_pose is None:
            decision = KeyframeDecision(True, 0.0, 0.0, 0.0)
        else:
            relative = np.linalg.inv(self._last_pose) @ pose
            distance = float(np.linalg.norm(relative[:3, 3]))
            angle = float(np.degrees(rotation_angle(relative[:3, :3])))
            interval = float(timestamp - self._last_time)
            cfg = self.config
            selected = (
                (cfg.min_distance_m is not None and distance >= cfg.min_distance_m)
                or (cfg.min_angle_deg is not None and angle >= cfg.min_angle_deg)
                or (cfg.max_interval_s is not None and interval >= cfg.max_interval_s)
            )
            decision = KeyframeDecision(selected, distance, angle, interval)
        if decision.is_keyframe:
            self._last_pose, self._last_time = pose.copy(), float(timestamp)
            self.count += 1
        return decision

    def select(self, pose: np.ndarray, timestamp: float) -> bool:
        return self.decide(pose, timestamp).is_keyframe
