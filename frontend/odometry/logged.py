"""Odometry from poses logged with the traverse, optionally with seeded, injected drift.

Logs whose poses are ground truth leave nothing for loop closure to correct; the drift
model turns them into realistic odometry: each relative motion between consecutive logged
poses is degraded (scale error, yaw bias per metre, random walks growing with sqrt of the
distance) and the degraded motions are composed from the first logged pose on.
"""

from __future__ import annotations

import numpy as np

from frontend.config import DriftConfig, LoggedOdometryConfig, PoseFileConfig
from frontend.frame import Frame
from frontend.odometry.base import OdometryStats
from ssmvpr_common.poses import pose_problem

AXES = {"x": 0, "y": 1, "z": 2}


def so3_exp(rotation_vector: np.ndarray) -> np.ndarray:
    """Rotation matrix of an axis-angle vector (Rodrigues)."""
    angle = float(np.linalg.norm(rotation_vector))
    if angle == 0.0:
        return np.eye(3)
    k = np.asarray(rotation_vector, dtype=np.float64) / angle
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew


class DriftModel:
    """Seeded degradation of one relative motion at a time (same seed, same drift)."""

    def __init__(self, config: DriftConfig) -> None:
        self.config = config
        self._rng = np.random.default_rng(config.seed)

    def degrade(self, delta: np.ndarray) -> np.ndarray:
        cfg = self.config
        distance = float(np.linalg.norm(delta[:3, 3]))
        out = delta.copy()
        out[:3, 3] *= 1.0 + cfg.translation_scale_error
        sigma_t = cfg.translation_noise_per_sqrt_m * np.sqrt(distance)
        out[:3, 3] += self._rng.normal(0.0, 1.0, 3) * sigma_t
        bias = np.zeros(3)
        bias[AXES[cfg.yaw_axis]] = cfg.yaw_bias_per_m * distance
        sigma_r = cfg.rotation_noise_per_sqrt_m * np.sqrt(distance)
        noise = self._rng.normal(0.0, 1.0, 3) * sigma_r
        out[:3, :3] = delta[:3, :3] @ so3_exp(bias + noise)
        return out


class LoggedPoseOdometry:
    """``update(frame)`` returns the frame's logged (or gt) pose, drifted if configured.

    A frame without a usable pose (missing, NaN, not a rotation) is counted and the
    previous output is held; the motion across the gap is applied at the next good pose.
    """

    def __init__(self, config: LoggedOdometryConfig | None = None, pose_config: PoseFileConfig | None = None) -> None:
        self.config = config or LoggedOdometryConfig()
        self.stats = OdometryStats()
        self._tolerance = (pose_config or PoseFileConfig()).rotation_tolerance
        self._drift = DriftModel(self.config.drift) if self.config.drift.enabled else None
        self._last_logged: np.ndarray | None = None
        self._pose = np.eye(4)

    @property
    def pose(self) -> np.ndarray:
        return self._pose.copy()

    def update(self, frame: Frame) -> np.ndarray:
        self.stats.updates += 1
        name = "logged_pose" if self.config.pose_source == "logged" else "gt_pose"
        logged = getattr(frame, name)
        where = frame.label
        if logged is None:
            self.stats.skip(f"no_{name}", f"{where}: no {name}; previous pose held")
            return self.pose
        problem = pose_problem(logged, self._tolerance)
        if problem is not None:
            self.stats.skip(f"invalid_{name}", f"{where}: {name} {problem}; previous pose held")
            return self.pose
        logged = np.asarray(logged, dtype=np.float64)
        if self._last_logged is None or self._drift is None:
            self._pose = logged.copy()
        else:
            delta = np.linalg.inv(self._last_logged) @ logged
            self._pose = self._pose @ self._drift.degrade(delta)
        self._last_logged = logged.copy()
        return self.pose
