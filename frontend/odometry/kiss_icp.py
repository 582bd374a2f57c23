"""LiDAR odometry: kiss-icp, behind input checks its C++ core does not do itself.

kiss-icp aborts the whole process (SOPHUS_ENSURE) when deskewing with all-equal per-point
times, and NaN points poison its voxel map. So every scan is cleaned here first: non-finite
points and the all-zero placeholders drivers publish for missing returns dropped,
range-filtered, and too-small scans skipped with a constant-velocity
prediction; per-point times are handed over only when they are real (finite, one per
point, not all equal), otherwise kiss-icp gets none and does not deskew that scan.
"""

from __future__ import annotations

import math

import numpy as np

from frontend.config import KissIcpConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.odometry.base import OdometryStats
from frontend.odometry.kiss_threads import claim_kiss_icp_threads

NO_TIMES = np.zeros(0, dtype=np.float64)


def kiss_config(config: KissIcpConfig):  # -> kiss_icp.config.KISSConfig
    """kiss-icp's own config object from ours (voxel size defaults to max_range / 100)."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.config.config import (
        AdaptiveThresholdConfig,
        DataConfig,
        MappingConfig,
        RegistrationConfig,
    )

    # kiss-icp's rule of thumb when no voxel size is given (see kiss_icp.config.load_config).
    voxel_size = config.voxel_size or config.max_range / 100.0
    return KISSConfig(
        data=DataConfig(max_range=config.max_range, min_range=config.min_range, deskew=config.deskew),
        mapping=MappingConfig(voxel_size=voxel_size, max_points_per_voxel=config.max_points_per_voxel),
        registration=RegistrationConfig(
            max_num_iterations=config.max_num_iterations,
            convergence_criterion=config.convergence_criterion,
            max_num_threads=config.max_num_threads,
        ),
        adaptive_threshold=AdaptiveThresholdConfig(
            fixed_threshold=config.fixed_threshold,
            initial_threshold=config.initial_threshold,
            min_motion_th=config.min_motion_th,
        ),
    )


class KissIcpOdometry:
    """``update(frame)`` registers ``frame.points`` with kiss-icp; returns the LiDAR pose.

    kept_voxel: the voxel size (m) at which the caller keeps scans for loop registration. When it
    is the one kiss-icp voxelises each scan at for its map (half its voxel size), `last_scan` is
    that voxelised scan (the same points the caller's voxel filter would give), so the scan is
    not filtered twice nor shipped whole out of the odometry's process."""

    def __init__(self, config: KissIcpConfig | None = None, kept_voxel: float | None = None) -> None:
        from kiss_icp.kiss_icp import KissICP  # heavy C++ extension: imported on use

        self.config = config or KissIcpConfig()
        self.stats = OdometryStats()
        claim_kiss_icp_threads(self.config.max_num_threads, "frontend.odometry.kiss_icp.max_num_threads")
        kiss = kiss_config(self.config)
        self._kiss = KissICP(kiss)
        map_voxel = kiss.mapping.voxel_size * 0.5  # KissICP.voxelize: the map gets the scan at this size
        self._reused_voxel = (
            kept_voxel if kept_voxel is not None and math.isclose(kept_voxel, map_voxel, rel_tol=1e-12) else None
        )
        self._map_points: np.ndarray | None = None
        if self._reused_voxel is not None:
            self._kiss_voxelize = self._kiss.voxelize  # kiss-icp's own, wrapped to keep what it computes
            self._kiss.voxelize = self._voxelize  # type: ignore[method-assign]
        self.last_scan: np.ndarray | None = None
        """The last registered scan, motion-compensated (deskewed) by kiss-icp; loop closure
        registration needs undistorted scans, and kiss-icp already computed this one."""
        self.last_scan_voxel: float | None = None
        """The voxel size `last_scan` is already filtered at (one point per voxel), or None."""

    @property
    def pose(self) -> np.ndarray:
        """Latest pose (identity before the first frame)."""
        return self._kiss.last_pose.copy()

    def update(self, frame: Frame) -> np.ndarray:
        self.stats.updates += 1
        points, times = self.clean(frame)
        self.last_scan = self.last_scan_voxel = self._map_points = None
        if points is None:
            return self._predict()
        previous_pose, previous_delta = self._kiss.last_pose.copy(), self._kiss.last_delta.copy()
        deskewed, _ = self._kiss.register_frame(points, times)
        if not np.all(np.isfinite(self._kiss.last_pose)):
            self.stats.skip("registration_failed", f"frame {frame.index}: kiss-icp returned a non-finite pose")
            self._kiss.last_pose, self._kiss.last_delta = previous_pose, previous_delta
            return self._predict()
        if self._map_points is not None:  # kiss-icp's voxelised scan, at the caller's size
            self.last_scan, self.last_scan_voxel = self._map_points, self._reused_voxel
        else:
            self.last_scan = np.asarray(deskewed)
        return self._kiss.last_pose.copy()

    def _voxelize(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """kiss-icp's own `voxelize`, keeping the map's voxelised scan it computes anyway."""
        source, self._map_points = self._kiss_voxelize(frame)
        return source, self._map_points

    def _predict(self) -> np.ndarray:
        """Pose for a skipped scan; kiss-icp's state follows so the next guess stays right."""
        if self.config.predict_on_skip:
            self._kiss.last_pose = self._kiss.last_pose @ self._kiss.last_delta
        return self._kiss.last_pose.copy()

    def clean(self, frame: Frame) -> tuple[np.ndarray | None, np.ndarray]:
        """Finite, in-range float64 points and usable per-point times (or None to skip), as
        `update` hands them to kiss-icp; a skip or a degraded scan is counted in `stats`."""
        where = frame.label
        if frame.points is None:
            self.stats.skip("no_points", f"{where}: no LiDAR scan; pose predicted")
            return None, NO_TIMES
        points = np.asarray(frame.points)
        if points.ndim != 2 or points.shape[1] != 3:
            raise FrontendInputError(f"{where}: points have shape {points.shape}, expected (N, 3)")
        points = points.astype(np.float64, copy=False)
        # A NaN or inf coordinate makes the range NaN or inf, and (0, 0, 0), how drivers publish a
        # missing return, makes it 0: one pass over the points drops all three, whatever min_range says
        # (this runs on every scan, on the odometry's critical path: a norm of a masked copy took 3-7 ms)
        with np.errstate(over="ignore", invalid="ignore"):
            ranges = np.sqrt(np.einsum("ij,ij->i", points, points))
        keep = np.isfinite(ranges) & (ranges > 0.0)
        keep &= (ranges >= self.config.min_range) & (ranges <= self.config.max_range)
        if keep.sum() < self.config.min_points:
            reason = "empty_scan" if len(points) == 0 else "too_few_valid_points"
            self.stats.skip(
                reason,
                f"{where}: {int(keep.sum())} of {len(points)} points finite and in range "
                f"(< min_points={self.config.min_points}); pose predicted",
            )
            return None, NO_TIMES
        times = NO_TIMES
        if self.config.deskew and frame.point_times is not None:
            raw = np.asarray(frame.point_times, dtype=np.float64).ravel()
            if raw.shape[0] == points.shape[0] and np.all(np.isfinite(raw[keep])):
                candidate = raw[keep]
                if candidate.max() > candidate.min():
                    times = np.ascontiguousarray(candidate)
            if times is NO_TIMES:
                self.stats.note("deskew_off", f"{where}: per-point times unusable; not deskewed")
        return np.ascontiguousarray(points[keep]), times
