"""Umeyama alignment, ATE / RPE / drift, timestamp association, loop precision / recall."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssmvpr_slam.backend.se3 import make_pose, rot_z
from ssmvpr_slam.evaluation.alignment import umeyama
from ssmvpr_slam.evaluation.config import LoopMetricsConfig
from ssmvpr_slam.evaluation.loop_metrics import classify_revisits, evaluate_loops, find_revisits
from ssmvpr_slam.evaluation.metrics import associate, ate, drift_per_100m, rpe


def circle(n: int = 100, radius: float = 20.0) -> np.ndarray:
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    poses = [make_pose(rot_z(a + np.pi / 2), [radius * np.cos(a), radius * np.sin(a), 0.1 * a]) for a in ang]
    return np.array(poses)


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_known_transform(with_scale):
    rng = np.random.default_rng(0)
    src = rng.normal(0, 10, (50, 3))
    rot = Rotation.from_rotvec([0.3, -0.7, 1.1]).as_matrix()
    trans = np.array([4.0, -2.0, 7.5])
    scale = 2.5 if with_scale else 1.0
    dst = scale * src @ rot.T + trans
    fit = umeyama(src, dst, with_scale=with_scale)
    np.testing.assert_allclose(fit.rotation, rot, atol=1e-12)
    np.testing.assert_allclose(fit.translation, trans, atol=1e-10)
    assert fit.scale == pytest.approx(scale, abs=1e-12)
    np.testing.assert_allclose(fit.apply_points(src), dst, atol=1e-10)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(1)
    src = rng.normal(0, 1, (30, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image
    fit = umeyama(src, dst)
    assert np.linalg.det(fit.rotation) == pytest.approx(1.0)


def test_umeyama_rejects_bad_input():
    with pytest.raises(ValueError, match="source"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="target"):
        umeyama(np.zeros((5, 3)), np.full((5, 3), np.nan))


def test_ate_is_zero_for_a_rigidly_moved_trajectory():
    ref = circle()
    moved = make_pose(rot_z(1.0), [3.0, 4.0, 5.0])[None] @ ref
    result = ate(ref, moved)
    assert result.stats.rmse < 1e-9
    assert ate(ref, moved, alignment="none").stats.rmse > 1.0


def test_ate_statistics_of_a_constant_offset_without_alignment():
    ref = circle()
    est = ref.copy()
    est[:, 0, 3] += 0.5
    stats = ate(ref, est, alignment="none").stats
    assert (stats.rmse, stats.mean, stats.median, stats.max) == pytest.approx((0.5,) * 4)
    json.dumps(ate(ref, est).to_dict())  # ready for metrics.json


def test_rpe_frames_and_metres():
    ref = circle(n=100)
    est = ref.copy()
    est[50:, :3, 3] += [1.0, 0.0, 0.0]  # one jump between frames 49 and 50
    by_frame = rpe(ref, est, delta=1)
    assert by_frame.translation.max == pytest.approx(1.0)
    assert by_frame.translation.n == 99
    assert by_frame.rotation_deg.max == pytest.approx(0.0, abs=1e-9)
    step = np.linalg.norm(ref[1, :3, 3] - ref[0, :3, 3])
    by_metre = rpe(ref, est, delta=5 * step * 0.999, unit="m")
    assert [j - i for i, j in by_metre.pairs] == [5] * len(by_metre.pairs)
    json.dumps(by_metre.to_dict())
    with pytest.raises(ValueError, match="delta"):
        rpe(ref, est, delta=1000, unit="m")


def test_rpe_rotation_error_in_degrees():
    ref = circle(n=10)
    est = ref @ make_pose(rot_z(np.radians(2.0)), [0, 0, 0])[None]
    est[1::2] = ref[1::2]
    assert rpe(ref, est, delta=1).rotation_deg.max == pytest.approx(2.0)


def test_drift_per_100m():
    steps = 300
    ref = np.array([make_pose(np.eye(3), [k * 1.0, 0, 0]) for k in range(steps)])
    est = np.array([make_pose(np.eye(3), [k * 1.02, 0, 0]) for k in range(steps)])  # 2% scale
    drift = drift_per_100m(ref, est)
    assert drift.translation_m_per_100m == pytest.approx(2.0, rel=1e-6)
    assert drift.segment_m == pytest.approx(100.0)
    short = drift_per_100m(ref[:50], est[:50])
    assert short.n_segments == 1 and short.translation_m_per_100m == pytest.approx(2.0)


def test_associate_timestamps():
    ref_t = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    est_t = np.array([0.301, 0.099, 5.0, 0.1005])
    ref_idx, est_idx = associate(ref_t, est_t, max_dt=0.01)
    assert list(zip(ref_idx.tolist(), est_idx.tolist())) == [(1, 1), (3, 0)]


def test_metric_inputs_are_validated():
    ref = circle(10)
    with pytest.raises(ValueError, match="associate"):
        ate(ref, ref[:5])
    bad = ref.copy()
    bad[3, 1, 1] = np.nan
    with pytest.raises(ValueError, match=r"est_poses\[3\]"):
        ate(ref, bad)


def loop_gt() -> np.ndarray:
    """Out and back along x: keyframe k at x=k for k<10, then back, x=19-k."""
    x = [k if k < 10 else 19 - k for k in range(20)]
    return np.array([[float(v), 0.0, 0.0] for v in x])


def test_revisits_respect_radius_and_gap():
    gt = loop_gt()
    # keyframe q revisits m = 19 - q; gap q - m = 2q - 19 >= 5 for q >= 12
    assert find_revisits(gt, radius=0.5, min_frame_gap=5).tolist() == list(range(12, 20))
    assert find_revisits(gt, radius=0.5, min_frame_gap=100).tolist() == []


def test_loop_precision_recall_per_query_keyframe():
    gt = loop_gt()
    cfg = LoopMetricsConfig(revisit_radius=0.5, correct_radius=1.5, min_frame_gap=5)
    loops = [
        (19, 0),  # exact: correct
        (18, 2),  # 1 m off: correct under the looser radius
        (17, 8),  # 6 m off: wrong
        (15, 4),  # correct, but query 15 also has ...
        (15, 9),  # ... a wrong loop, so it counts as a false positive
    ]
    res = evaluate_loops(gt, loops, cfg)
    assert res.n_revisits == 8
    assert res.n_query_keyframes == 4
    assert res.n_true_positive_queries == 2  # queries 19 and 18
    assert res.n_false_positive_queries == 2  # queries 17 and 15
    assert res.precision == pytest.approx(0.5)
    assert res.n_recalled_revisits == 3  # 19, 18, 15 have a correct loop
    assert res.recall == pytest.approx(3 / 8)
    assert res.loop_correct == [True, True, False, True, False]
    json.dumps(res.to_dict(include_lists=True))


def test_loop_metrics_undefined_ratios_are_none():
    res = evaluate_loops(loop_gt(), [], LoopMetricsConfig(revisit_radius=0.5, min_frame_gap=100))
    assert res.precision is None and res.recall is None


def test_loop_metrics_bad_input():
    with pytest.raises(ValueError, match=r"loops\[0\]"):
        evaluate_loops(loop_gt(), [(30, 1)])
    with pytest.raises(ValueError, match="correct_radius"):
        LoopMetricsConfig(revisit_radius=5.0, correct_radius=1.0)


def _drive(points: list[tuple[float, float]], step: float = 1.0) -> np.ndarray:
    """(N, 3) positions every `step` metres along a polyline."""
    out = []
    for (x0, y0), (x1, y1) in zip(points[:-1], points[1:]):
        n = int(round(np.hypot(x1 - x0, y1 - y0) / step))
        t = np.arange(n) / n
        out.append(np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0), np.zeros(n)], axis=1))
    return np.concatenate(out)


def test_revisits_split_by_direction_and_camera_visibility():
    # east along y=0, a U-turn onto y=2 (inside the 5 m radius) driving west: reverse revisits;
    # then east again on y=0: forward revisits; finally south across the street: a crossing
    gt = _drive([(0, 0), (100, 0), (100, 2), (0, 2), (0, 0), (100, 0), (100, 20), (50, 20), (50, -30)])
    cfg = LoopMetricsConfig(revisit_radius=5.0, correct_radius=10.0, min_frame_gap=20, view_angle_deg=45.0)
    revisits = find_revisits(gt, cfg.revisit_radius, cfg.min_frame_gap)
    kinds = classify_revisits(gt, revisits, cfg.revisit_radius, cfg.min_frame_gap, cfg.view_angle_deg)
    west = (gt[kinds.ids, 1] == 2.0) & (gt[kinds.ids, 0] > 5) & (gt[kinds.ids, 0] < 95)  # westward, mid-street
    second_east = (kinds.ids > 210) & (kinds.ids < 300) & (gt[kinds.ids, 1] == 0)
    crossing = kinds.ids >= 374  # the last leg crosses the streets at x = 50, heading south
    assert west.sum() > 50 and second_east.sum() > 50 and crossing.any()
    assert not kinds.forward[west].any() and not kinds.visible[west].any()
    assert kinds.forward[second_east].all() and kinds.visible[second_east].all()
    assert not kinds.visible[crossing].any()  # seen at right angles: no camera overlap

    # recall over all revisits vs over what a forward camera can see: loops only on the forward leg
    loops = [(int(q), int(q) - 202) for q in kinds.ids[second_east]]
    ev = evaluate_loops(gt, loops, cfg)
    assert ev.precision == 1.0
    assert ev.n_visible_revisits < ev.n_revisits
    assert ev.recall < 0.6 < ev.recall_visible
    fwd, rev = ev.by_direction["forward"], ev.by_direction["reverse"]
    assert fwd["recalled"] == len(loops) and rev["recalled"] == 0
    assert rev["visible"] == 0 and rev["recall_visible"] is None
    assert fwd["revisits"] + rev["revisits"] == ev.n_revisits

    # with a rear camera the westward leg becomes visible too; the crossing never is
    rear = classify_revisits(gt, revisits, cfg.revisit_radius, cfg.min_frame_gap, cfg.view_angle_deg, rear_camera=True)
    westward = west & (kinds.ids < 210)  # (the crossing leg passes y = 2 once, heading south)
    assert rear.visible[westward].all() and rear.visible[second_east].all() and not rear.visible[crossing].any()
    assert np.array_equal(rear.forward, kinds.forward)
    ev_rear = evaluate_loops(gt, loops, cfg, rear_camera=True)
    assert ev_rear.n_visible_revisits > ev.n_visible_revisits
    assert ev_rear.by_direction["reverse"]["visible"] >= westward.sum()
