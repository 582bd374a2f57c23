#!/usr/bin/env python3
"""Upper bound of the trajectory correction: perfect loop closures on a simulated traverse; prints JSON.

Loop closure can only remove odometry error that differs between two visits of a place. This
bench separates that from detector quality: it builds the pose graph exactly as the pipeline
does (same keyframes, odometry factors, robust kernel), but with an ideal detector and an ideal
registration: every ground-truth revisit keyframe gets a loop factor to its nearest earlier
keyframe carrying the exact ground-truth relative pose, weighted like a LiDAR ICP loop. The
optimised ATE it reaches is the best any loop detector could do with that odometry.

    python tools/bench_loop_oracle.py [--odometry kiss-icp|logged|both] [--frames N] [--config FILE]
                                      [--sim-config SIM_YAML] [--route POSES_FILE]
                                      [--poses-frame auto|camera|body]

--config is the SLAM config (odometry, keyframes, pose graph, evaluation); the traverse is the
demo's unless --sim-config (a SimulationConfig YAML) and / or --route (a poses file) say otherwise.

Reported per odometry: ATE (SE(3)-aligned RMSE) of odometry alone and after the ideal loops,
with forward revisits only and with forward and reverse revisits, the per-axis RMSE of what
remains, and the KITTI devkit's relative error (% and deg / 100 m over 100..800 m segments of
keyframes; null on traverses shorter than 100 m) of the odometry and of each optimised trajectory.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from frontend.keyframes import KeyframeSelector  # noqa: E402
from frontend.odometry import make_odometry  # noqa: E402
from frontend.simulation import SimulationConfig, TraverseSimulator, ground_truth_revisits  # noqa: E402
from ssmvpr_slam.backend import PoseGraph  # noqa: E402
from ssmvpr_slam.backend.noise import sigmas6  # noqa: E402
from ssmvpr_slam.config.slam import SlamConfig, load_config  # noqa: E402
from ssmvpr_slam.evaluation.metrics import ate, kitti_relative_error  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _sim_options import add_simulation_options, simulation_config  # noqa: E402

ODOMETRY_KINDS = {"kiss-icp": "kiss_icp", "logged": "logged"}


def keyframe_trajectories(config: SlamConfig, kind: str, sim_config: SimulationConfig) -> tuple[np.ndarray, np.ndarray]:
    """(ground truth, odometry) poses of the keyframes the pipeline would select."""
    data = sim_config.model_dump()  # no images; scans only for kiss-icp
    data["camera"] = {**data["camera"], "enabled": False}
    data["lidar"] = {**data["lidar"], "enabled": kind == "kiss_icp"}
    sim_config = SimulationConfig.model_validate(data)
    odometry_config = config.frontend.odometry.model_copy(update={"kind": kind})
    odometry = make_odometry(odometry_config, config.frontend.pose_files)
    selector = KeyframeSelector(config.frontend.keyframes)
    gt, odom = [], []
    for frame in TraverseSimulator(sim_config).frames():
        pose = odometry.update(frame)
        if selector.select(pose, frame.timestamp):
            gt.append(frame.gt_pose)
            odom.append(pose)
    return np.array(gt), np.array(odom)


def ideal_loops(gt: np.ndarray, radius: float, min_gap: int) -> list[tuple[int, int, bool]]:
    """(match, query, is_forward) for every keyframe with a ground-truth revisit."""
    yaw = np.arctan2(gt[:, 1, 0], gt[:, 0, 0])
    matches = ground_truth_revisits(gt[:, :3, 3], radius, min_gap)
    return [
        (int(m), q, bool(abs(np.angle(np.exp(1j * (yaw[q] - yaw[m])))) <= np.pi / 2))
        for q, m in enumerate(matches)
        if m >= 0
    ]


def optimise(
    config: SlamConfig, kind: str, gt: np.ndarray, odom: np.ndarray, loops: list[tuple[int, int, bool]]
) -> np.ndarray:
    """Stream keyframes and ideal loops through the pipeline's pose graph (with the odometry
    sigmas the pipeline uses for `kind`), in time order."""
    lidar = config.backend.registration.lidar
    sigmas = sigmas6(lidar.rot_sigma, lidar.trans_sigma)
    by_query = {q: m for m, q, _ in loops}
    graph = PoseGraph(config.backend.pose_graph.for_odometry(kind))
    for k, pose in enumerate(odom):
        graph.add_keyframe(k, pose)
        if k in by_query:
            m = by_query[k]
            graph.add_loop(m, k, np.linalg.inv(gt[m]) @ gt[k], sigmas=sigmas)
        graph.update()
    poses = graph.finalize()
    return np.array([poses[k] for k in range(len(odom))])


def axis_rmse(gt: np.ndarray, est: np.ndarray) -> dict[str, float]:
    aligned = ate(gt, est).aligned_poses
    rms = np.sqrt(np.mean((aligned[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=0))
    return {axis: round(float(v), 3) for axis, v in zip("xyz", rms)}


def kitti(config: SlamConfig, gt: np.ndarray, est: np.ndarray) -> dict[str, object]:
    """KITTI relative error over keyframes, with the evaluation config's lengths and step."""
    traj = config.evaluation.trajectory
    return kitti_relative_error(gt, est, tuple(traj.kitti_lengths_m), traj.kitti_step_frames).to_dict()


def bench(config: SlamConfig, kind: str, sim_config: SimulationConfig) -> dict[str, object]:
    start = time.perf_counter()
    gt, odom = keyframe_trajectories(config, kind, sim_config)
    loops_cfg = config.evaluation.loops
    loops = ideal_loops(gt, loops_cfg.revisit_radius, loops_cfg.min_frame_gap)
    base = ate(gt, odom).stats.rmse
    out: dict[str, object] = {
        "keyframes": len(gt),
        "odometry_ate_m": round(base, 3),
        "odometry_ate_xyz_m": axis_rmse(gt, odom),
        "odometry_kitti_rel_error": kitti(config, gt, odom),
    }
    for label, subset in (("forward", [lp for lp in loops if lp[2]]), ("forward_and_reverse", loops)):
        est = optimise(config, kind, gt, odom, subset)
        value = ate(gt, est).stats.rmse
        out[label] = {
            "loops": len(subset),
            "optimised_ate_m": round(value, 3),
            "ratio": round(value / base, 3) if base > 0 else None,
            "optimised_ate_xyz_m": axis_rmse(gt, est),
            "optimised_kitti_rel_error": kitti(config, gt, est),
        }
    out["seconds"] = round(time.perf_counter() - start, 1)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--odometry", choices=[*ODOMETRY_KINDS, "both"], default="both")
    parser.add_argument("--config", type=Path, default=None, help="SLAM YAML config (default preset otherwise)")
    add_simulation_options(parser, ("--sim-config",))
    args = parser.parse_args(argv)
    if args.frames is not None and args.frames < 2:
        parser.error("--frames must be at least 2")
    config = load_config(args.config)
    sim_config = simulation_config(parser, args)
    kinds = list(ODOMETRY_KINDS) if args.odometry == "both" else [args.odometry]
    result = {name: bench(config, ODOMETRY_KINDS[name], sim_config) for name in kinds}
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
