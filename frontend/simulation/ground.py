"""The ground as a raster around the street centre line: distance to the road, position along
it, and the district, looked up per pixel by the camera.

Streets follow the route rather than a grid, so "is this asphalt?" is a question about the
distance to a polyline. Answering it with a k-d tree per frame would cost more than the rest
of the image, so it is answered once, at build time, on a grid of ``resolution_m`` cells and
interpolated bilinearly (the distance field is smooth away from the centre line itself).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

_MAX_CELLS = 6_000_000
_FAR_M = 40.0  # beyond this from any street the ground is plain plot / grass
OPEN = 2  # district code used outside the raster


@dataclass
class GroundMap:
    origin: np.ndarray  # (2,) world xy of cell (0, 0)
    resolution: float
    dist: np.ndarray  # (H, W) float32 metres to the nearest centre-line point, capped
    along: np.ndarray  # (H, W) float32 arc length of that point
    district: np.ndarray  # (H, W) int8 district code of that point
    height: np.ndarray  # (H, W) float32 road height of that point: the terrain follows the roads

    @classmethod
    def build(
        cls,
        centre_xy: np.ndarray,
        along: np.ndarray,
        district: np.ndarray,
        centre_z: np.ndarray | None = None,
        resolution_m: float = 0.5,
    ) -> GroundMap:
        lo = centre_xy.min(axis=0) - _FAR_M
        hi = centre_xy.max(axis=0) + _FAR_M
        res = resolution_m
        while np.prod(np.ceil((hi - lo) / res)) > _MAX_CELLS:
            res *= 1.5
        w, h = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
        gx = lo[0] + res * np.arange(w)
        gy = lo[1] + res * np.arange(h)
        tree = cKDTree(centre_xy)
        centre_z = np.zeros(len(centre_xy)) if centre_z is None else centre_z
        dist = np.full((h, w), _FAR_M, np.float32)
        near = np.zeros((h, w), np.int64)
        for r0 in range(0, h, 256):  # bounded memory for long routes
            xx, yy = np.meshgrid(gx, gy[r0 : r0 + 256])
            d, i = tree.query(np.column_stack([xx.ravel(), yy.ravel()]))
            d = np.minimum(d, _FAR_M)
            dist[r0 : r0 + 256] = d.reshape(xx.shape)
            near[r0 : r0 + 256] = i.reshape(xx.shape)
        far = dist >= _FAR_M
        dist_code = np.where(far, OPEN, district[near]).astype(np.int8)
        return cls(lo, res, dist, along[near].astype(np.float32), dist_code, centre_z[near].astype(np.float32))

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Terrain height at world (x, y): bilinear in the raster, the edge value outside it."""
        h, w = self.height.shape
        fx = np.clip(
            (np.asarray(x, np.float32) - np.float32(self.origin[0])) / np.float32(self.resolution), 0, w - 1.001
        )
        fy = np.clip(
            (np.asarray(y, np.float32) - np.float32(self.origin[1])) / np.float32(self.resolution), 0, h - 1.001
        )
        ix, iy = fx.astype(np.int64), fy.astype(np.int64)
        ax, ay = fx - ix, fy - iy
        g = self.height
        return (
            (g[iy, ix] * (1 - ax) + g[iy, ix + 1] * ax) * (1 - ay)
            + (g[iy + 1, ix] * (1 - ax) + g[iy + 1, ix + 1] * ax) * ay
        ).astype(np.float32)

    def lookup(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(distance to the street centre, arc length along it, district) at world (x, y)."""
        h, w = self.dist.shape
        fx = (np.asarray(x, np.float32) - np.float32(self.origin[0])) / np.float32(self.resolution)
        fy = (np.asarray(y, np.float32) - np.float32(self.origin[1])) / np.float32(self.resolution)
        inside = (fx >= 0) & (fy >= 0) & (fx < w - 1) & (fy < h - 1)
        fx = np.clip(fx, 0, w - 1.001)
        fy = np.clip(fy, 0, h - 1.001)
        ix, iy = fx.astype(np.int64), fy.astype(np.int64)
        ax, ay = fx - ix, fy - iy
        d = self.dist
        dist = (d[iy, ix] * (1 - ax) + d[iy, ix + 1] * ax) * (1 - ay) + (
            d[iy + 1, ix] * (1 - ax) + d[iy + 1, ix + 1] * ax
        ) * ay
        jx, jy = np.rint(fx).astype(np.int64), np.rint(fy).astype(np.int64)
        along = self.along[jy, jx]
        district = self.district[jy, jx]
        dist = np.where(inside, dist, np.float32(_FAR_M))
        district = np.where(inside, district, np.int8(OPEN))
        return dist.astype(np.float32), along, district
