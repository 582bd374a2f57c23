"""What a keyframe keeps of its LiDAR scan for loop registration, held compactly.

A keyframe's scan is voxelised to the local-map voxel (kiss-icp's `map_downsample_factor` x
`voxel_size`, 0.5 m by default) and kept for the whole run, so it dominates what a keyframe
costs: about 12,600 points, 151 kB in float32 on the demo. Held as int16 centimetres in the
sensor frame it is half that. The rounding (at most 5 mm per axis) is a hundredth of the voxel
the points already stand for, and ICP matches them against 1 m voxels. Points beyond
`MAX_RANGE_M` cannot be held and are dropped: no LiDAR that loop registration uses reaches it
(`registration.lidar.max_range` crops the local maps at 100 m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SCALE_M = 0.01
"""Metres per stored unit: centimetres."""
MAX_RANGE_M = np.iinfo(np.int16).max * SCALE_M
"""327.67 m: the farthest coordinate an int16 in centimetres holds."""


@dataclass(frozen=True)
class KeptScan:
    """(N, 3) int16 centimetres in the sensor frame; `points` gives metres back."""

    centimetres: np.ndarray

    def __post_init__(self) -> None:
        cm = self.centimetres
        if cm.dtype != np.int16 or cm.ndim != 2 or cm.shape[1] != 3:
            raise ValueError(f"kept scan: need (N, 3) int16 centimetres, got {cm.dtype} {cm.shape}")

    @classmethod
    def from_points(cls, points: np.ndarray) -> KeptScan | None:
        """The kept form of sensor-frame points in metres (non-finite and out-of-range ones
        dropped); None when none is left."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        keep = np.isfinite(points).all(axis=1) & (np.abs(points) < MAX_RANGE_M).all(axis=1)
        if not keep.any():
            return None
        return cls(np.rint(points[keep] / SCALE_M).astype(np.int16))

    @property
    def points(self) -> np.ndarray:
        """(N, 3) float64 metres, as registration and saved maps take them."""
        return self.centimetres.astype(np.float64) * SCALE_M

    @property
    def nbytes(self) -> int:
        return int(self.centimetres.nbytes)

    def __len__(self) -> int:
        return len(self.centimetres)


def keep_scan(points: np.ndarray | None, voxel_m: float) -> KeptScan | None:
    """A scan voxelised (kiss-icp's voxel filter, one point per voxel) and held as `KeptScan`."""
    if points is None or len(points) == 0:
        return None
    from kiss_icp.voxelization import voxel_down_sample

    finite = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    finite = finite[np.isfinite(finite).all(axis=1)]
    if not len(finite):
        return None
    return KeptScan.from_points(voxel_down_sample(finite, voxel_m))
