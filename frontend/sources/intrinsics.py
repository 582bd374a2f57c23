"""A camera's pinhole calibration as a log carries it (ROS CameraInfo, KITTI calib.txt).

K follows the ROS / OpenCV convention: pixel (u, v) = K @ (x/z, y/z, 1), with the centre of the
top-left pixel at (0, 0), for the images as the log stores them (native resolution).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


def k_problem(values: Any) -> str | None:
    """Why `values` (9 numbers, row-major, or 3x3) is no usable pinhole K; None when it is.

    An all-zero K is what an uncalibrated ROS camera publishes: it is refused like any other
    K whose use would put pixels in the wrong place."""
    try:
        k = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        return "K is not numeric"
    if k.size != 9:
        return f"K has {k.size} values, expected 9"
    k = k.reshape(3, 3)
    if not np.all(np.isfinite(k)):
        return "K is not finite"
    if not np.any(k):
        return "K is all zeros (an uncalibrated camera)"
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        return f"K has focal lengths fx={k[0, 0]:g}, fy={k[1, 1]:g}; both must be > 0"
    if k[1, 0] != 0 or not np.array_equal(k[2], [0.0, 0.0, 1.0]):
        return "K is not upper triangular with last row 0 0 1"
    return None


@dataclass(frozen=True, eq=False)
class CameraIntrinsics:
    """A valid pinhole K (3x3 float64, read-only) and the image size it was given for, when known.

    Built only from a K that passes :func:`k_problem` (ValueError otherwise), so a held
    CameraIntrinsics is always usable."""

    k: np.ndarray
    width: int | None = None
    height: int | None = None

    def __post_init__(self) -> None:
        problem = k_problem(self.k)
        if problem is not None:
            raise ValueError(problem)
        k = np.array(self.k, dtype=np.float64).reshape(3, 3)
        k.setflags(write=False)
        object.__setattr__(self, "k", k)
        for name in ("width", "height"):
            size = getattr(self, name)
            if size is not None and size <= 0:
                raise ValueError(f"{name} {size} must be > 0 (or None when unknown)")


def pinhole(
    fx: float, fy: float, cx: float, cy: float, width: int | None = None, height: int | None = None
) -> CameraIntrinsics:
    """The CameraIntrinsics of a distortion-free pinhole camera."""
    return CameraIntrinsics(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), width, height)
