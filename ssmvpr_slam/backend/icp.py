"""Scan-to-map alignment for loop closures with kiss-icp's registration, tried from several
yaw seeds, plus the quality measures that decide whether to trust the result.

Uses kiss-icp's public Python pieces (`VoxelHashMap`, `Registration`, `voxel_down_sample`).
Points are checked here first (finite, shape (N, 3), enough of them): kiss-icp's C++ side
aborts the process on some bad inputs instead of raising.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from kiss_icp.mapping import VoxelHashMap
from kiss_icp.registration import Registration
from kiss_icp.voxelization import voxel_down_sample
from scipy.spatial import cKDTree

from frontend.odometry.kiss_threads import claim_kiss_icp_threads
from ssmvpr_slam.backend.config import LidarRegistrationConfig


def clean_points(name: str, points: object, max_range: float) -> np.ndarray:
    """(N, 3) float64 points with NaN / inf rows and points beyond `max_range` dropped.

    Wrong shapes are a ValueError naming `name`; too few points is left to the caller, which
    rejects the loop with a reason instead of failing.
    """
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not a numeric (N, 3) array ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {arr.shape}")
    arr = arr[:, :3]
    arr = arr[np.all(np.isfinite(arr), axis=1)]
    arr = arr[np.linalg.norm(arr, axis=1) <= max_range]
    return np.ascontiguousarray(arr)


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to (N, 3) points."""
    return points @ pose[:3, :3].T + pose[:3, 3]


@dataclass(frozen=True)
class IcpCloud:
    """A cleaned cloud and kiss-icp's two resolutions of it, made once per registration."""

    raw: np.ndarray
    dense: np.ndarray
    """At the map resolution: what the voxel map holds, and what the final quality is scored on."""
    sparse: np.ndarray
    """At the ICP source resolution: what is aligned, and what screening is scored on."""


@dataclass(frozen=True)
class IcpOutcome:
    """The alignment the seed search chose: `pose` maps source points into the target frame.

    inlier_ratio / rmse are measured from the down-sampled source to the raw target."""

    pose: np.ndarray
    inlier_ratio: float
    rmse: float
    seed_index: int
    n_source: int
    n_target: int


class SeededIcp:
    """Aligns a source cloud to a target cloud from several initial guesses.

    Each seed is screened with a short run of the first stage (cheap, scored on the sparse
    cloud); the `refine_top_k` best then run every stage, and the best refined seed wins. With
    `seed_search: first_acceptable` (seeds come nearest-the-guess first) the first seed, and any
    seed whose screening reaches `early_stop_inlier_ratio`, runs every stage at once, and the
    search ends there when the result passes acceptance (`min_inlier_ratio`, `max_rmse`): a
    right guess costs one seed even where a short screening leaves it unconverged, as on a
    reverse revisit. It takes the acceptable alias nearest the guess where a scene has one;
    `best` screens every seed.
    """

    def __init__(self, config: LidarRegistrationConfig) -> None:
        self.config = config
        claim_kiss_icp_threads(config.max_num_threads, "backend.registration.lidar.max_num_threads")
        self._screen = self._registration(config.screening_iterations)
        self._stages = [self._registration(stage.max_iterations) for stage in config.stages]

    def _registration(self, iterations: int) -> Registration:
        return Registration(
            max_num_iterations=iterations,
            convergence_criterion=self.config.convergence_criterion,
            max_num_threads=self.config.max_num_threads,
        )

    def prepare(self, points: np.ndarray) -> IcpCloud:
        """A cleaned cloud with its dense and sparse versions, as kiss-icp makes them."""
        cfg = self.config
        if len(points) == 0:
            return IcpCloud(points, points, points)
        dense = np.asarray(voxel_down_sample(points, cfg.voxel_size * cfg.map_downsample_factor), dtype=np.float64)
        sparse = np.asarray(voxel_down_sample(dense, cfg.voxel_size * cfg.source_downsample_factor), dtype=np.float64)
        return IcpCloud(points, dense, sparse)

    def passes(self, outcome: IcpOutcome) -> bool:
        """Whether an alignment is good enough to be accepted as a loop."""
        return outcome.inlier_ratio >= self.config.min_inlier_ratio and outcome.rmse <= self.config.max_rmse

    def align(self, source: IcpCloud, target: IcpCloud, seeds: list[np.ndarray]) -> IcpOutcome:
        """Align `source` to `target` (both from `prepare`); each must hold >= min_points dense
        points (the caller checks)."""
        if not seeds:
            raise ValueError("seeds: need at least one initial guess")
        cfg = self.config
        target_dense, source_dense, source_sparse = target.dense, source.dense, source.sparse
        voxel_map = VoxelHashMap(cfg.voxel_size, cfg.max_range, cfg.max_points_per_voxel)
        voxel_map.add_points(target_dense)
        # Quality against the raw map, independent of voxel size. An unbalanced tree builds in
        # about half the time and finds the same nearest neighbours.
        tree = cKDTree(target.raw, balanced_tree=False, compact_nodes=False)
        early_stop = cfg.min_inlier_ratio if cfg.early_stop_inlier_ratio is None else cfg.early_stop_inlier_ratio
        first_acceptable = cfg.seed_search == "first_acceptable"

        def refine(index: int, pose: np.ndarray) -> IcpOutcome:
            for stage, registration in zip(cfg.stages, self._stages):
                pose = registration.align_points_to_map(
                    points=source_sparse,
                    voxel_map=voxel_map,
                    initial_guess=pose,
                    max_correspondance_distance=stage.max_correspondence_distance,
                    kernel=stage.kernel,
                )
            ratio, rmse = self._quality(tree, source_dense, pose)
            return IcpOutcome(pose, ratio, rmse, index, len(source_dense), len(target_dense))

        first = cfg.stages[0]
        screened: list[tuple[float, int, np.ndarray]] = []
        refined: dict[int, IcpOutcome] = {}
        for index, seed in enumerate(seeds):
            pose = self._screen.align_points_to_map(
                points=source_sparse,
                voxel_map=voxel_map,
                initial_guess=np.asarray(seed, dtype=np.float64),
                max_correspondance_distance=first.max_correspondence_distance,
                kernel=first.kernel,
            )
            ratio, _ = self._quality(tree, source_sparse, pose)
            screened.append((ratio, index, pose))
            if first_acceptable and (index == 0 or ratio >= early_stop):
                refined[index] = refine(index, pose)
                if self.passes(refined[index]):
                    return refined[index]
        screened.sort(key=lambda item: (-item[0], item[1]))
        for _, index, pose in screened[: cfg.refine_top_k]:
            if index not in refined:
                refined[index] = refine(index, pose)
        return max(refined.values(), key=lambda o: (o.inlier_ratio, -o.rmse, -o.seed_index))

    def _quality(self, tree: cKDTree, source: np.ndarray, pose: np.ndarray) -> tuple[float, float]:
        """Share of source points with a target neighbour within inlier_distance, and the RMSE
        of those inlier distances."""
        bound = np.nextafter(self.config.inlier_distance, np.inf)  # the search prunes beyond it
        dist, _ = tree.query(transform_points(pose, source), k=1, distance_upper_bound=bound)
        inliers = dist <= self.config.inlier_distance
        ratio = float(np.mean(inliers))
        rmse = float(np.sqrt(np.mean(dist[inliers] ** 2))) if inliers.any() else float("inf")
        return ratio, rmse
