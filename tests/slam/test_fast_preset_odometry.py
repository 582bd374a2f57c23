"""The presets' kiss-icp settings, lighter than kiss-icp's own (the default's 10 points a voxel and
`fast`'s 1.5 m voxels with 5, both stopping at a 1e-3 update), still track: on simulated scans
and on real KITTI Velodyne pairs.

Its speed and whole-traverse accuracy are benchmarks (`tools/bench_odometry.py --slam-config
fast`, docs/slam_demo.md); these tests guard against a setting that loses track.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from frontend.frame import Frame
from frontend.odometry import KissIcpOdometry
from frontend.simulation import TraverseSimulator, default_demo_config
from frontend.sources.kitti_source import read_velodyne
from ssmvpr_slam.config.slam import load_config

# KITTI 00 ground truth of the two pairs (PROVENANCE.txt), camera frame (x right, y down, z
# forward) turned into the Velodyne's axes (x forward, y left, z up).
KITTI_PAIRS = {("000094", "000095"): (0.474, -0.021, 0.012), ("000198", "000199"): (0.514, 0.053, 0.016)}


@pytest.fixture(scope="module", params=["default", "fast"])
def preset(request: pytest.FixtureRequest) -> str:
    return request.param


def test_the_preset_tracks_a_simulated_traverse(preset: str) -> None:
    odometry = KissIcpOdometry(load_config(preset).frontend.odometry.kiss_icp)
    frames = list(TraverseSimulator(default_demo_config(max_frames=60, camera={"enabled": False})).frames())
    est = np.array([odometry.update(f) for f in frames])
    gt = np.array([f.gt_pose for f in frames])
    est = np.einsum("ij,njk->nik", gt[0], est)
    travelled = np.linalg.norm(np.diff(gt[:, :2, 3], axis=0), axis=1).sum()
    assert travelled > 50
    err = np.linalg.norm(est[:, :2, 3] - gt[:, :2, 3], axis=1)
    assert err.max() < 0.02 * travelled, (preset, err.max(), travelled)


@pytest.mark.parametrize("pair", list(KITTI_PAIRS))
def test_the_preset_registers_real_kitti_scans(shared_dir: Path, preset: str, pair: tuple[str, str]) -> None:
    velodyne = shared_dir / "data" / "kitti00_scans" / "velodyne"
    odometry = KissIcpOdometry(load_config(preset).frontend.odometry.kiss_icp)
    for k, name in enumerate(pair):
        pose = odometry.update(Frame(k, 0.1 * k, points=read_velodyne(velodyne / f"{name}.bin")))
    error = np.linalg.norm(pose[:3, 3] - np.array(KITTI_PAIRS[pair]))
    assert error < 0.04, (preset, pair, pose[:3, 3])
