"""Logged-pose odometry: exact without drift, seeded and growing drift with it."""

from __future__ import annotations

import numpy as np
import pytest

from frontend.config import DriftConfig, LoggedOdometryConfig, OdometryConfig
from frontend.frame import Frame
from frontend.odometry import LoggedPoseOdometry, make_odometry
from frontend.odometry.logged import so3_exp


def _square_loop(steps_per_side: int = 50, step_m: float = 1.0) -> list[np.ndarray]:
    """Ground-truth poses driving around a square (z up) and back to the start."""
    poses, pose = [], np.eye(4)
    for _side in range(4):
        for k in range(steps_per_side):
            poses.append(pose.copy())
            motion = np.eye(4)
            motion[0, 3] = step_m
            if k == steps_per_side - 1:
                motion[:3, :3] = so3_exp([0, 0, np.pi / 2])
            pose = pose @ motion
    return poses


def _frames(poses: list[np.ndarray], field: str = "logged_pose") -> list[Frame]:
    return [Frame(i, 0.1 * i, **{field: p}) for i, p in enumerate(poses)]


DRIFT = DriftConfig(
    enabled=True,
    seed=7,
    translation_scale_error=0.02,
    yaw_bias_per_m=0.002,
    translation_noise_per_sqrt_m=0.01,
    rotation_noise_per_sqrt_m=0.001,
)


def _run(config: LoggedOdometryConfig, frames: list[Frame]) -> np.ndarray:
    odometry = make_odometry(OdometryConfig(kind="logged", logged=config))
    assert isinstance(odometry, LoggedPoseOdometry)
    return np.stack([odometry.update(f) for f in frames])


def test_without_drift_poses_pass_through() -> None:
    poses = _square_loop(5)
    out = _run(LoggedOdometryConfig(), _frames(poses))
    np.testing.assert_allclose(out, np.stack(poses), atol=1e-12)


def test_gt_pose_source() -> None:
    poses = _square_loop(3)
    out = _run(LoggedOdometryConfig(pose_source="gt"), _frames(poses, "gt_pose"))
    np.testing.assert_allclose(out, np.stack(poses))


def test_drift_is_seeded_and_grows_with_distance() -> None:
    poses = _square_loop()
    frames = _frames(poses)
    first = _run(LoggedOdometryConfig(drift=DRIFT), frames)
    again = _run(LoggedOdometryConfig(drift=DRIFT), frames)
    other = _run(LoggedOdometryConfig(drift=DRIFT.model_copy(update={"seed": 8})), frames)
    np.testing.assert_array_equal(first, again)
    assert not np.allclose(first, other)
    np.testing.assert_allclose(first[0], poses[0])  # starts on the logged pose
    errors = np.linalg.norm(first[:, :3, 3] - np.stack(poses)[:, :3, 3], axis=1)
    assert 0 < errors[10] < errors[50] < errors[100] < errors[199]
    assert errors[-1] > 2.0  # the loop no longer closes: something for loop closure to fix


def test_scale_error_alone_is_deterministic() -> None:
    poses = _square_loop(10)
    drift = DriftConfig(enabled=True, translation_scale_error=0.1)
    out = _run(LoggedOdometryConfig(drift=drift), _frames(poses))
    np.testing.assert_allclose(out[5][:3, 3], 1.1 * poses[5][:3, 3], atol=1e-12)


def test_nan_and_missing_poses_hold_the_previous_pose() -> None:
    poses = _square_loop(5)
    frames = _frames(poses)
    frames[3].logged_pose = np.full((4, 4), np.nan)
    frames[4].logged_pose = None
    odometry = LoggedPoseOdometry()
    out = [odometry.update(f) for f in frames]
    np.testing.assert_array_equal(out[3], out[2])
    np.testing.assert_array_equal(out[4], out[2])
    np.testing.assert_allclose(out[5], poses[5])  # motion across the gap is kept
    assert odometry.stats.skipped == {"invalid_logged_pose": 1, "no_logged_pose": 1}


def test_drift_config_is_validated() -> None:
    with pytest.raises(ValueError):
        DriftConfig(translation_scale_error=-1.5)
    with pytest.raises(ValueError):
        DriftConfig(rotation_noise_per_sqrt_m=-0.1)
