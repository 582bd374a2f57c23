"""Cross-check against evo (installed here as the reference implementation, not skipped).

If evo is missing this module fails at import with a clear message: the comparison is part
of the contract, not an optional extra.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

try:
    from evo.core import metrics as evo_metrics
    from evo.core import sync as evo_sync
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface
except ImportError as exc:  # pragma: no cover - evo is a declared test dependency here
    raise ImportError(
        f"evo is required for tests/slam/evaluation/test_evo_compat.py (pip install 'ssmvpr-slam[evo]'): {exc}"
    ) from exc

from ssmvpr_common.trajectory_io import read_kitti, read_tum, write_kitti, write_tum
from ssmvpr_slam.backend.se3 import make_pose, rot_z
from ssmvpr_slam.evaluation.metrics import ate, rpe


@pytest.fixture(scope="module")
def trajectories():
    rng = np.random.default_rng(42)
    n = 200
    ang = np.linspace(0, 3 * np.pi, n)
    ref = np.array([make_pose(rot_z(a), [30 * np.cos(a), 20 * np.sin(a), 0.05 * k]) for k, a in enumerate(ang)])
    est = ref.copy()
    drift = np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0)
    tilt = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.002, (n, 3)), axis=0)).as_matrix()
    est[:, :3, 3] += drift
    est[:, :3, :3] = est[:, :3, :3] @ tilt
    world = make_pose(Rotation.from_rotvec([0.1, -0.2, 0.8]).as_matrix(), [5.0, -3.0, 1.0])
    est = world[None] @ est  # a different world frame, as odometry has
    stamps = np.arange(n) * 0.1
    return stamps, ref, est


def evo_traj(stamps, poses):
    return PoseTrajectory3D(poses_se3=list(poses), timestamps=np.asarray(stamps))


def test_ate_matches_evo_ape(trajectories):
    stamps, ref, est = trajectories
    traj_ref, traj_est = evo_traj(stamps, ref), evo_traj(stamps, est)
    traj_est.align(traj_ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    theirs = ape.get_all_statistics()
    ours = ate(ref, est).stats
    for name in ("rmse", "mean", "median", "std", "min", "max"):
        assert getattr(ours, name) == pytest.approx(theirs[name], rel=1e-9, abs=1e-12), name


def test_sim3_ate_matches_evo(trajectories):
    stamps, ref, est = trajectories
    scaled = est.copy()
    scaled[:, :3, 3] *= 0.7
    traj_ref, traj_est = evo_traj(stamps, ref), evo_traj(stamps, scaled)
    traj_est.align(traj_ref, correct_scale=True)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    assert ate(ref, scaled, alignment="sim3").stats.rmse == pytest.approx(
        ape.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-9
    )


@pytest.mark.parametrize(("delta", "all_pairs"), [(1, False), (10, False), (10, True)])
def test_rpe_matches_evo(trajectories, delta, all_pairs):
    stamps, ref, est = trajectories
    for relation, ours_of in (
        (evo_metrics.PoseRelation.translation_part, lambda r: r.translation),
        (evo_metrics.PoseRelation.rotation_angle_deg, lambda r: r.rotation_deg),
    ):
        metric = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=all_pairs)
        metric.process_data((evo_traj(stamps, ref), evo_traj(stamps, est)))
        theirs = metric.get_all_statistics()
        ours = ours_of(rpe(ref, est, delta=delta, all_pairs=all_pairs))
        assert ours.n == len(metric.error)
        for name in ("rmse", "mean", "max"):
            assert getattr(ours, name) == pytest.approx(theirs[name], rel=1e-7, abs=1e-9)


def test_files_are_interchangeable_with_evo(tmp_path, trajectories):
    stamps, ref, _ = trajectories
    write_tum(tmp_path / "ours.tum", stamps, ref)
    theirs = file_interface.read_tum_trajectory_file(str(tmp_path / "ours.tum"))
    np.testing.assert_allclose(np.array(theirs.poses_se3), ref, atol=1e-8)
    file_interface.write_tum_trajectory_file(str(tmp_path / "evo.tum"), copy.deepcopy(theirs))
    t_back, back = read_tum(tmp_path / "evo.tum")
    np.testing.assert_allclose(back, ref, atol=1e-6)
    np.testing.assert_allclose(t_back, stamps, atol=1e-6)

    write_kitti(tmp_path / "ours.kitti", ref)
    kitti = file_interface.read_kitti_poses_file(str(tmp_path / "ours.kitti"))
    np.testing.assert_allclose(np.array(kitti.poses_se3), ref, atol=1e-7)
    file_interface.write_kitti_poses_file(str(tmp_path / "evo.kitti"), kitti)
    np.testing.assert_allclose(read_kitti(tmp_path / "evo.kitti"), ref, atol=1e-5)


def test_association_agrees_with_evo_sync(trajectories):
    from ssmvpr_slam.evaluation.metrics import associate

    stamps, ref, est = trajectories
    est_stamps = stamps[::3] + 0.004
    ref_idx, est_idx = associate(stamps, est_stamps, max_dt=0.01)
    traj_ref, traj_est = evo_sync.associate_trajectories(
        evo_traj(stamps, ref), evo_traj(est_stamps, est[::3]), max_diff=0.01
    )
    np.testing.assert_allclose(stamps[ref_idx], traj_ref.timestamps)
    np.testing.assert_allclose(est_stamps[est_idx], traj_est.timestamps)
