"""kiss-icp odometry: accurate on a synthetic room, and never crashes on bad scans."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from frontend.config import KissIcpConfig, OdometryConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.odometry import KissIcpOdometry, Odometry, make_odometry
from frontend.odometry.logged import so3_exp

ROOM = (30.0, 12.0, 4.0)  # length, width, height (m)
PILLARS = [(-5.0, 2.0), (6.0, -3.0)]
CONFIG = KissIcpConfig(max_range=40.0, voxel_size=0.4, max_num_threads=2)


def _room_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points sampled on the walls, floor, ceiling and two round pillars of a room."""
    length, width, height = ROOM
    per = n // 8
    u = rng.uniform
    faces = [
        np.c_[u(-length / 2, length / 2, per), np.full(per, -width / 2), u(0, height, per)],
        np.c_[u(-length / 2, length / 2, per), np.full(per, width / 2), u(0, height, per)],
        np.c_[np.full(per, -length / 2), u(-width / 2, width / 2, per), u(0, height, per)],
        np.c_[np.full(per, length / 2), u(-width / 2, width / 2, per), u(0, height, per)],
        np.c_[u(-length / 2, length / 2, per), u(-width / 2, width / 2, per), np.zeros(per)],
        np.c_[u(-length / 2, length / 2, per), u(-width / 2, width / 2, per), np.full(per, height)],
    ]
    for cx, cy in PILLARS:
        a = u(0, 2 * np.pi, per)
        faces.append(np.c_[cx + 0.5 * np.cos(a), cy + 0.5 * np.sin(a), u(0, height, per)])
    return np.vstack(faces)


def _sensor_pose(k: int) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = so3_exp([0.0, 0.0, 0.02 * k])
    pose[:3, 3] = [-8.0 + 0.4 * k, 0.5 * np.sin(0.1 * k), 1.5]
    return pose


def _scan(k: int, rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    world = _room_points(rng, n)
    sensor = (np.linalg.inv(_sensor_pose(k)) @ np.c_[world, np.ones(len(world))].T).T[:, :3]
    return sensor + rng.normal(0.0, 0.01, sensor.shape)


def test_tracks_a_known_path_in_a_synthetic_room() -> None:
    rng = np.random.default_rng(0)
    odometry = make_odometry(OdometryConfig(kind="kiss_icp", kiss_icp=CONFIG))
    assert isinstance(odometry, KissIcpOdometry) and isinstance(odometry, Odometry)
    start = _sensor_pose(0)
    for k in range(20):
        estimate = odometry.update(Frame(k, 0.1 * k, points=_scan(k, rng)))
        truth = np.linalg.inv(start) @ _sensor_pose(k)  # odometry starts at the identity
        assert np.linalg.norm(estimate[:3, 3] - truth[:3, 3]) < 0.1
        angle_error = np.arccos(np.clip((np.trace(estimate[:3, :3].T @ truth[:3, :3]) - 1) / 2, -1, 1))
        assert angle_error < np.radians(1.0)
    assert np.linalg.norm(estimate[:3, 3]) > 7.0  # it really moved
    assert odometry.stats.updates == 20 and not odometry.stats.skipped


def test_empty_nan_and_missing_scans_predict_without_crashing() -> None:
    rng = np.random.default_rng(1)
    odometry = KissIcpOdometry(CONFIG)
    assert np.array_equal(odometry.update(Frame(0, 0.0, points=np.zeros((0, 3)))), np.eye(4))
    poses = [odometry.update(Frame(k, 0.1 * k, points=_scan(k, rng))) for k in range(1, 5)]
    step = np.linalg.inv(poses[-2]) @ poses[-1]
    all_nan = np.full((500, 3), np.nan)
    predicted = odometry.update(Frame(5, 0.5, points=all_nan))
    np.testing.assert_allclose(predicted, poses[-1] @ step, atol=1e-9)  # constant velocity
    odometry.update(Frame(6, 0.6, points=None))
    few = _scan(7, rng)[:5]
    odometry.update(Frame(7, 0.7, points=few))
    mixed = _scan(8, rng)
    mixed[::3] = np.inf
    after = odometry.update(Frame(8, 0.8, points=mixed))
    truth = np.linalg.inv(_sensor_pose(1)) @ _sensor_pose(8)
    assert np.all(np.isfinite(after))
    assert np.linalg.norm(after[:3, 3] - truth[:3, 3]) < 0.2  # recovered after the gap
    skipped = odometry.stats.skipped
    assert skipped["empty_scan"] == 1 and skipped["no_points"] == 1
    assert skipped["too_few_valid_points"] == 2  # all-NaN and 5-point scans


@pytest.mark.parametrize("min_range", [0.0, 0.5])
def test_zero_placeholder_points_are_dropped_even_with_min_range_zero(min_range: float) -> None:
    """Drivers publish (0, 0, 0) for a missing return; kept, they pin the map to the sensor."""
    rng = np.random.default_rng(3)
    config = CONFIG.model_copy(update={"min_range": min_range})
    odometry = KissIcpOdometry(config)
    for k in range(8):
        scan = _scan(k, rng)
        padded = np.vstack([scan, np.zeros((2 * len(scan), 3))])  # two thirds of the points missing
        estimate = odometry.update(Frame(k, 0.1 * k, points=padded))
    truth = np.linalg.inv(_sensor_pose(0)) @ _sensor_pose(7)
    assert np.linalg.norm(estimate[:3, 3] - truth[:3, 3]) < 0.1
    assert odometry.update(Frame(8, 0.8, points=np.zeros((5000, 3)))) is not None
    assert odometry.stats.skipped == {"too_few_valid_points": 1}


def test_hold_instead_of_predict() -> None:
    rng = np.random.default_rng(2)
    odometry = KissIcpOdometry(CONFIG.model_copy(update={"predict_on_skip": False}))
    poses = [odometry.update(Frame(k, 0.1 * k, points=_scan(k, rng))) for k in range(3)]
    np.testing.assert_array_equal(odometry.update(Frame(3, 0.3, points=np.zeros((0, 3)))), poses[-1])


def test_unusable_point_times_switch_deskew_off() -> None:
    rng = np.random.default_rng(3)
    odometry = KissIcpOdometry(CONFIG)
    scan = _scan(0, rng)
    odometry.update(Frame(0, 0.0, points=scan, point_times=np.zeros(len(scan))))
    odometry.update(Frame(1, 0.1, points=scan, point_times=np.zeros(3)))  # wrong length
    odometry.update(Frame(2, 0.2, points=scan, point_times=np.linspace(0, 0.1, len(scan))))
    assert odometry.stats.notes["deskew_off"] == 2


def test_all_zero_point_times_do_not_abort_the_process() -> None:
    """kiss-icp aborts (SOPHUS_ENSURE) on deskew with all-equal times: run in a child
    process so that a regression fails this test instead of killing the test session."""
    code = textwrap.dedent(
        """
        import numpy as np
        from frontend.config import KissIcpConfig
        from frontend.frame import Frame
        from frontend.odometry import KissIcpOdometry
        rng = np.random.default_rng(0)
        odometry = KissIcpOdometry(KissIcpConfig(deskew=True, voxel_size=1.0, max_num_threads=1))
        for k in range(3):
            points = rng.uniform(-10, 10, (2000, 3))
            odometry.update(Frame(k, 0.1 * k, points=points, point_times=np.zeros(len(points))))
        print("survived", odometry.stats.notes["deskew_off"])
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "survived 3" in result.stdout


def test_malformed_points_are_an_input_error() -> None:
    with pytest.raises(FrontendInputError, match=r"frame 4 .*shape \(10, 4\)"):
        KissIcpOdometry(CONFIG).update(Frame(4, 0.4, points=np.zeros((10, 4))))


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="min_range"):
        KissIcpConfig(min_range=50.0, max_range=10.0)
    with pytest.raises(ValueError):
        KissIcpConfig(unknown_field=1)


def test_the_points_kept_are_the_finite_nonzero_ones_within_range() -> None:
    """The one-pass filter against the rule written out point by point: non-finite coordinates,
    (0, 0, 0), and ranges outside [min_range, max_range] (bounds kept) are dropped."""
    config = KissIcpConfig(min_range=0.5, max_range=100.0)
    rng = np.random.default_rng(3)
    points = rng.normal(scale=40.0, size=(3000, 3))
    points[:40] = [[np.nan, 1, 1], [np.inf, 0, 0], [-np.inf, 1, 2], [0, 0, 0], [1e200, 0, 0], [100.0, 0, 0],
                   [0, 0.5, 0], [0, 0, 0.4999], [60, 80, 0.001], [0, 0, -100.0]] * 4  # fmt: skip
    expected = [p for p in points if np.all(np.isfinite(p)) and np.any(p != 0) and 0.5 <= math.hypot(*p) <= 100.0]
    kept, _ = KissIcpOdometry(config).clean(Frame(0, 0.0, points=points))
    assert kept is not None
    np.testing.assert_array_equal(kept, np.array(expected))
    assert [100.0, 0, 0] in kept.tolist() and [0, 0.5, 0] in kept.tolist() and [0, 0, -100.0] in kept.tolist()
