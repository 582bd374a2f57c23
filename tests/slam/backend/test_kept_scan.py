"""A keyframe keeps its voxelised scan as packed int16 centimetres: under a third of float32
on a real scan, within 5 mm, exact through a checkpoint, and metres again wherever registration
or a saved map reads it. The points come back as a set (sorted), not in their order."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from kiss_icp.voxelization import voxel_down_sample

from ssmvpr_slam.backend.kept_scan import MAX_RANGE_M, KeptScan, keep_scan
from ssmvpr_slam.checkpoint import loading as checkpoint_loading
from ssmvpr_slam.checkpoint import saving as checkpoint
from ssmvpr_slam.run_result import Keyframe, RunResult


def _street_scan(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform([-90, -90, -3], [90, 90, 12], size=(n, 3))


def _rows(points: np.ndarray) -> np.ndarray:
    return points[np.lexsort(points.T[::-1])]


def test_points_come_back_within_half_a_centimetre_as_a_set() -> None:
    points = _street_scan(5000, 0)
    kept = KeptScan.from_points(points)
    assert kept is not None and len(kept) == 5000
    back = kept.points
    assert back.shape == (5000, 3) and back.dtype == np.float64
    assert np.abs(back - _rows(np.rint(points * 100) / 100)).max() <= 1e-12  # the same centimetres, sorted
    assert np.abs(_rows(back) - back).max() == 0  # sorted by x, then y, then z
    assert kept.nbytes < 5000 * 3 * 2  # even uniform noise packs below plain int16


def test_a_real_kitti_scan_packs_to_under_a_third_of_float32(shared_dir: Path) -> None:
    raw = np.fromfile(shared_dir / "data" / "kitti00_scans" / "velodyne" / "000094.bin", np.float32).reshape(-1, 4)
    kept = keep_scan(raw[:, :3], 0.5)
    assert kept is not None and len(kept) > 5000
    assert kept.nbytes <= 0.65 * len(kept) * 3 * 2  # the demo city: 0.58 of plain int16
    voxelised = voxel_down_sample(raw[:, :3].astype(np.float64), 0.5)  # what keep_scan is given to hold
    np.testing.assert_array_equal(kept.centimetres, _rows(np.rint(voxelised * 100).astype(np.int16)))


def test_non_finite_and_unholdable_points_are_dropped() -> None:
    points = np.array([[1.0, 2.0, 3.0], [np.nan, 0, 0], [MAX_RANGE_M + 1, 0, 0], [0, -400.0, 0], [-5.25, 0.004, 2]])
    kept = KeptScan.from_points(points)
    assert kept is not None
    np.testing.assert_allclose(kept.points, [[-5.25, 0.0, 2.0], [1.0, 2.0, 3.0]])
    assert KeptScan.from_points(np.array([[np.inf, 0, 0]])) is None
    assert keep_scan(None, 0.5) is None and keep_scan(np.zeros((0, 3)), 0.5) is None


def test_extreme_coordinates_survive_the_delta_coding() -> None:
    """Deltas between int16 values overflow int16; they wrap, and the running sum wraps back."""
    cm = np.array([[-32768, 32767, -32768], [32767, -32768, 32767], [0, 0, 0], [32767, 32767, -32768]], np.int16)
    np.testing.assert_array_equal(KeptScan.from_centimetres(cm).centimetres, _rows(cm))


@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_single_point_scans_round_trip(n: int) -> None:
    cm = np.full((n, 3), -7, np.int16)
    kept = KeptScan.from_centimetres(cm)
    assert len(kept) == n
    np.testing.assert_array_equal(kept.centimetres, cm)
    assert kept.points.shape == (n, 3)


def test_keep_scan_voxelises_to_one_point_per_voxel() -> None:
    points = _street_scan(20000, 1)
    kept = keep_scan(points, 5.0)
    assert kept is not None
    assert len(kept) == len(np.unique(np.floor(points / 5.0), axis=0)) < 20000


@pytest.mark.parametrize("own_process", [False, True])
def test_the_odometry_s_own_voxelised_scan_is_kept_as_filtering_it_again_would(
    shared_dir: Path, own_process: bool
) -> None:
    """kiss-icp voxelises each scan for its map at half its voxel size, which is the size a
    keyframe keeps its scan at by default (0.5 m): that scan is kept as it is, not filtered a
    second time (nor shipped whole out of the odometry's process), and it must be the very scan
    filtering the deskewed one gives. Another size gets the deskewed scan, as before."""
    from frontend.config import KissIcpConfig, OdometryConfig
    from frontend.frame import Frame
    from frontend.odometry import make_odometry

    velodyne = shared_dir / "data" / "kitti00_scans" / "velodyne"
    frames = [Frame(k, 0.1 * k, points=np.fromfile(velodyne / f"{94 + k:06d}.bin", np.float32).reshape(-1, 4)[:, :3])
              for k in range(2)]  # two consecutive real scans  # fmt: skip
    config = OdometryConfig(kind="kiss_icp", kiss_icp=KissIcpConfig(max_num_threads=1))  # voxel 1 m: map at 0.5
    plain = make_odometry(config)
    reused = make_odometry(config, own_process=own_process, kept_voxel=0.5)
    other = make_odometry(config, own_process=own_process, kept_voxel=0.3)
    try:
        for frame in frames:
            plain.update(frame)
            reused.update(frame)
            other.update(frame)
            assert plain.last_scan is not None and reused.last_scan_voxel == 0.5 and other.last_scan_voxel is None
            assert len(reused.last_scan) < len(plain.last_scan) / 3
            filtered = keep_scan(plain.last_scan, 0.5)
            kept = keep_scan(reused.last_scan, 0.5, voxelised=True)
            assert filtered is not None and kept is not None
            np.testing.assert_array_equal(kept.centimetres, filtered.centimetres)
            np.testing.assert_allclose(other.last_scan, plain.last_scan, rtol=0, atol=1e-9)  # the deskewed scan
    finally:
        for odometry in (reused, other):
            getattr(odometry, "close", lambda: None)()


@pytest.mark.parametrize("bad", [np.zeros((4, 3), np.float32), np.zeros((4, 2), np.int16), np.zeros(3, np.int16)])
def test_a_kept_scan_refuses_anything_but_int16_xyz(bad: np.ndarray) -> None:
    with pytest.raises(ValueError, match="int16"):
        KeptScan.from_centimetres(bad)


def test_a_checkpoint_holds_the_kept_scans_exactly(tmp_path: Path) -> None:
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = np.arange(3.0)
    scans = [KeptScan.from_points(_street_scan(100 + k, k)) for k in range(2)] + [None]
    kfs = tuple(Keyframe(k, k, float(k), poses[k], None, scans[k], None) for k in range(3))
    result = RunResult(kfs, (), np.arange(3.0), poses, poses)
    (tmp_path / "keyframes.npz").write_bytes(checkpoint._npz(checkpoint._keyframe_arrays(result)))
    back = checkpoint_loading._keyframes(checkpoint_loading._load_npz(tmp_path / "keyframes.npz"), tmp_path / "images")
    for before, after in zip(kfs, back):
        if before.scan is None:
            assert after.scan is None
        else:
            assert after.scan is not None and after.scan.centimetres.dtype == np.int16
            assert np.array_equal(after.scan.centimetres, before.scan.centimetres)
