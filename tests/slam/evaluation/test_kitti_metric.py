"""KITTI odometry relative error (the devkit's protocol): known scale and yaw-rate errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ssmvpr_slam.backend.se3 import make_pose, rot_z
from ssmvpr_slam.evaluation.metrics import KITTI_LENGTHS_M, kitti_relative_error

STEP_M = 0.5  # divides every KITTI length: straight-line segments end exactly at L
CURVE_STEP_M = 0.37  # divides none: no ties between path distance and L on the curve


def integrate(step_m: float, curvature: np.ndarray, scale: float = 1.0, yaw_error_per_m: float = 0.0) -> np.ndarray:
    """Planar poses from body-frame steps: forward `scale * step_m`, turn by the step's heading change."""
    poses = [np.eye(4)]
    for kappa in curvature:
        step = make_pose(rot_z((kappa + yaw_error_per_m) * step_m), [scale * step_m, 0.0, 0.0])
        poses.append(poses[-1] @ step)
    return np.array(poses)


def straight(length_m: float = 1000.0, **kw: float) -> np.ndarray:
    return integrate(STEP_M, np.zeros(int(round(length_m / STEP_M))), **kw)


def curved(length_m: float = 1000.0, **kw: float) -> np.ndarray:
    """A gentle S-bend: curvature swings +-1/2000 m^-1, so chords stay close to the arc."""
    s = np.arange(int(round(length_m / CURVE_STEP_M))) * CURVE_STEP_M
    return integrate(CURVE_STEP_M, np.sin(2 * np.pi * s / 600.0) / 2000.0, **kw)


def devkit_reference(
    gt: np.ndarray, est: np.ndarray, lengths=KITTI_LENGTHS_M, step: int = 10
) -> tuple[float, float, int]:
    """Independent transcription of the devkit's calcSequenceErrors (plain loops, acos, its error order)."""
    dist = [0.0]
    for k in range(1, len(gt)):
        dist.append(dist[-1] + float(np.linalg.norm(gt[k, :3, 3] - gt[k - 1, :3, 3])))
    t_errs, r_errs = [], []
    for first in range(0, len(gt), step):
        for length in lengths:
            last = next((k for k in range(first, len(gt)) if dist[k] >= dist[first] + length), None)
            if last is None:
                continue
            delta_gt = np.linalg.inv(gt[first]) @ gt[last]
            delta_est = np.linalg.inv(est[first]) @ est[last]
            error = np.linalg.inv(delta_est) @ delta_gt
            d = 0.5 * (np.trace(error[:3, :3]) - 1.0)
            r_errs.append(np.arccos(max(min(d, 1.0), -1.0)) / length)
            t_errs.append(np.linalg.norm(error[:3, 3]) / length)
    return 100.0 * float(np.mean(t_errs)), float(np.degrees(np.mean(r_errs))) * 100.0, len(t_errs)


def test_one_percent_scale_error_on_a_straight_line():
    gt = straight()
    result = kitti_relative_error(gt, straight(scale=1.01))
    assert result.translation_pct == pytest.approx(1.0, rel=1e-9)
    assert result.rotation_deg_per_100m == pytest.approx(0.0, abs=1e-9)
    # first frames every 10 poses = 5 m; a segment of L fits while its start is <= 1000 - L
    for entry in result.per_length:
        assert entry.n_segments == int((1000.0 - entry.length_m) // (10 * STEP_M)) + 1
        assert entry.translation_pct == pytest.approx(1.0, rel=1e-9)
    assert result.n_segments == sum(e.n_segments for e in result.per_length)
    assert result.path_length_m == pytest.approx(1000.0)


def test_one_percent_scale_error_on_a_curve():
    gt = curved()
    est = curved(scale=1.01)
    result = kitti_relative_error(gt, est)
    # a scale error stretches the chord |p_j - p_i|, while the devkit divides by the path length
    # L: 1 % * chord / L, which a gentle curve keeps within a few hundredths of 1 %
    assert result.translation_pct == pytest.approx(1.0, abs=0.02)
    t_pct, r_rate, n = devkit_reference(gt, est)
    assert result.translation_pct == pytest.approx(t_pct, rel=1e-9)
    assert result.rotation_deg_per_100m == pytest.approx(r_rate, abs=1e-6)
    assert result.n_segments == n
    chords = [np.linalg.norm(gt[j, :3, 3] - gt[i, :3, 3]) for i, j in result.pairs]
    expected = 1.0 * np.array(chords) / result.segment_lengths_m
    np.testing.assert_allclose(result.translation_errors_pct, expected, rtol=1e-9)


@pytest.mark.parametrize(("route", "step_m"), [(straight, STEP_M), (curved, CURVE_STEP_M)])
def test_constant_yaw_rate_error(route, step_m):
    deg_per_100m = 1.5
    gt = route()
    est = route(yaw_error_per_m=np.radians(deg_per_100m) / 100.0)
    result = kitti_relative_error(gt, est)
    # the estimate turns c * s more over s metres; a segment of nominal length L spans
    # s = (j - i) * step in [L, L + step), and the devkit divides by L
    travelled = np.array([(j - i) * step_m for i, j in result.pairs])
    expected = deg_per_100m * travelled / result.segment_lengths_m
    np.testing.assert_allclose(result.rotation_errors_deg_per_100m, expected, rtol=1e-6)
    assert result.rotation_deg_per_100m == pytest.approx(deg_per_100m, rel=step_m / 100.0)
    for entry in result.per_length:
        assert entry.rotation_deg_per_100m == pytest.approx(deg_per_100m, rel=step_m / entry.length_m)
    assert result.translation_pct > 0.1  # a heading error bends the path away
    t_pct, r_rate, _ = devkit_reference(gt, est)
    assert result.translation_pct == pytest.approx(t_pct, rel=1e-9)
    assert result.rotation_deg_per_100m == pytest.approx(r_rate, rel=1e-6)


def test_identical_and_rigidly_moved_estimates_have_no_error():
    gt = curved()
    for est in (gt.copy(), make_pose(rot_z(0.7), [30.0, -4.0, 2.0])[None] @ gt):
        result = kitti_relative_error(gt, est)
        assert result.n_segments > 0
        assert result.translation_pct == pytest.approx(0.0, abs=1e-9)
        assert result.rotation_deg_per_100m == pytest.approx(0.0, abs=1e-6)


def test_matches_the_devkit_on_a_noisy_3d_trajectory():
    rng = np.random.default_rng(3)
    gt = curved(600.0)
    gt[:, 2, 3] = 3.0 * np.sin(np.arange(len(gt)) / 150.0)  # some climb, non-planar
    noise = [make_pose(rot_z(rng.normal(0, 2e-3)), rng.normal(0, 0.02, 3)) for _ in gt]
    est = gt @ np.array(noise)
    result = kitti_relative_error(gt, est, step_frames=7)
    t_pct, r_rate, n = devkit_reference(gt, est, step=7)
    assert result.n_segments == n
    assert result.translation_pct == pytest.approx(t_pct, rel=1e-9)
    assert result.rotation_deg_per_100m == pytest.approx(r_rate, rel=1e-4)
    assert kitti_relative_error(gt, est, step_frames=1).n_segments > n  # every first frame


def test_route_shorter_than_the_shortest_segment():
    gt = straight(80.0)
    result = kitti_relative_error(gt, straight(80.0, scale=1.01))
    assert result.n_segments == 0 and result.pairs == []
    assert np.isnan(result.translation_pct) and np.isnan(result.rotation_deg_per_100m)
    assert all(e.n_segments == 0 and np.isnan(e.translation_pct) for e in result.per_length)
    out = result.to_dict()
    assert out["translation_pct"] is None and out["per_length"]["100"]["translation_pct"] is None
    json.dumps(out, allow_nan=False)  # metrics.json is strict JSON
    # custom lengths reach into short routes
    assert kitti_relative_error(gt, straight(80.0, scale=1.01), lengths=(50.0,)).translation_pct == pytest.approx(1.0)


def test_to_dict_is_json_ready():
    out = kitti_relative_error(straight(), straight(scale=1.01)).to_dict()
    json.dumps(out, allow_nan=False)
    assert set(out["per_length"]) == {"100", "200", "300", "400", "500", "600", "700", "800"}
    assert out["translation_pct"] == pytest.approx(1.0) and out["step_frames"] == 10
    assert out["n_segments"] == sum(v["n_segments"] for v in out["per_length"].values())


def test_inputs_are_validated():
    gt = straight(200.0)
    with pytest.raises(ValueError, match=r"gt: expected shape \(N, 4, 4\)"):
        kitti_relative_error(gt[:, :3, :], gt)
    with pytest.raises(ValueError, match=r"est: expected shape \(N, 4, 4\)"):
        kitti_relative_error(gt, gt[:, :, :3])
    bad = gt.copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(ValueError, match=r"est\[3\]: contains NaN or inf"):
        kitti_relative_error(gt, bad)
    with pytest.raises(ValueError, match=r"gt\[3\]: contains NaN or inf"):
        kitti_relative_error(bad, gt)
    with pytest.raises(ValueError, match="associate"):
        kitti_relative_error(gt, gt[:-1])
    with pytest.raises(ValueError, match="at least 2"):
        kitti_relative_error(gt[:1], gt[:1])
    for lengths in ((), (100.0, -5.0), (100.0, float("nan")), (100.0, 100.0)):
        with pytest.raises(ValueError, match="lengths"):
            kitti_relative_error(gt, gt, lengths=lengths)
    for step in (0, 2.5):
        with pytest.raises(ValueError, match="step_frames"):
            kitti_relative_error(gt, gt, step_frames=step)
