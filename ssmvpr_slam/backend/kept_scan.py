"""What a keyframe keeps of its LiDAR scan for loop registration, held compactly.

A keyframe's scan is voxelised to the local-map voxel (kiss-icp's `map_downsample_factor` x
`voxel_size`, 0.5 m by default) and kept for the whole run, so it dominates what a keyframe
costs: about 12,600 points, 151 kB in float32 on the demo. Held as int16 centimetres in the
sensor frame it is half that. The rounding (at most 5 mm per axis) is a hundredth of the voxel
the points already stand for, and ICP matches them against 1 m voxels. Points beyond
`MAX_RANGE_M` cannot be held and are dropped: no LiDAR that loop registration uses reaches it
(`registration.lidar.max_range` crops the local maps at 100 m).

The centimetres are then sorted, delta-coded along each axis, split into high and low bytes
and deflated: 1.7x smaller again on the demo city (about 42 kB a keyframe instead of 72), for
about 1 ms a keyframe to pack and 0.3 ms a scan to unpack when a loop's local map is built.
The points come back sorted, not in their scan order. Registration treats them as a set, but
kiss-icp's voxel filter keeps the first point of each voxel, so the order picks which point
stands for a voxel when a local map is down-sampled: poses move by millimetres, deterministically.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np

SCALE_M = 0.01
"""Metres per stored unit: centimetres."""
MAX_RANGE_M = np.iinfo(np.int16).max * SCALE_M
"""327.67 m: the farthest coordinate an int16 in centimetres holds."""
_LEVEL = 1  # zlib: level 1 packs within 3% of level 6 at a third of the time


@dataclass(frozen=True)
class KeptScan:
    """N points as sorted int16 centimetres in the sensor frame, packed (see the module
    docstring); `centimetres` and `points` unpack them."""

    packed: bytes = field(repr=False)
    count: int

    @classmethod
    def from_centimetres(cls, centimetres: np.ndarray) -> KeptScan:
        """Pack (N, 3) int16 centimetres (the order is not kept)."""
        cm = np.asarray(centimetres)
        if cm.dtype != np.int16 or cm.ndim != 2 or cm.shape[1] != 3:
            raise ValueError(f"kept scan: need (N, 3) int16 centimetres, got {cm.dtype} {cm.shape}")
        biased = cm.astype(np.int64) + 32768  # 0..65535 per axis: one sortable 48-bit key
        planes = cm[np.argsort((biased[:, 0] << 32) | (biased[:, 1] << 16) | biased[:, 2], kind="stable")].T
        deltas = np.ascontiguousarray(np.diff(planes.astype(np.int32), axis=1, prepend=0), dtype="<i2")  # wraps
        hi_lo = np.ascontiguousarray(deltas.view(np.uint8).reshape(3, -1, 2).transpose(0, 2, 1))
        return cls(zlib.compress(hi_lo.tobytes(), _LEVEL), len(cm))

    @classmethod
    def from_points(cls, points: np.ndarray) -> KeptScan | None:
        """The kept form of sensor-frame points in metres (non-finite and out-of-range ones
        dropped); None when none is left."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        keep = np.isfinite(points).all(axis=1) & (np.abs(points) < MAX_RANGE_M).all(axis=1)
        if not keep.any():
            return None
        return cls.from_centimetres(np.rint(points[keep] / SCALE_M).astype(np.int16))

    @property
    def centimetres(self) -> np.ndarray:
        """(N, 3) int16, sorted by x, then y, then z."""
        hi_lo = np.frombuffer(zlib.decompress(self.packed), dtype=np.uint8).reshape(3, 2, self.count)
        deltas = np.ascontiguousarray(hi_lo.transpose(0, 2, 1)).view("<i2").reshape(3, self.count)
        return np.cumsum(deltas, axis=1, dtype=np.int16).T.copy()

    @property
    def points(self) -> np.ndarray:
        """(N, 3) float64 metres, as registration and saved maps take them."""
        return self.centimetres.astype(np.float64) * SCALE_M

    @property
    def nbytes(self) -> int:
        return len(self.packed)

    def __len__(self) -> int:
        return self.count


def keep_scan(points: np.ndarray | None, voxel_m: float, voxelised: bool = False) -> KeptScan | None:
    """A scan voxelised (kiss-icp's voxel filter, one point per voxel) and held as `KeptScan`;
    voxelised: `points` already went through that filter at `voxel_m` (the odometry's own)."""
    if points is None or len(points) == 0:
        return None
    from kiss_icp.voxelization import voxel_down_sample

    finite = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    finite = finite[np.isfinite(finite).all(axis=1)]
    if not len(finite):
        return None
    return KeptScan.from_points(finite if voxelised else voxel_down_sample(finite, voxel_m))
