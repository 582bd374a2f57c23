"""SE(3) checks and small helpers shared by the back end and the evaluation.

Inputs are validated here, in numpy, so that bad data becomes a one-line ValueError naming
the input instead of an abort inside GTSAM or kiss-icp.
"""

from __future__ import annotations

import numpy as np

DEFAULT_ROTATION_TOLERANCE = 1e-4
"""Same default as `PoseGraphConfig.rotation_tolerance`; callers pass their config's value."""


def as_pose(name: str, pose: object, tol: float = DEFAULT_ROTATION_TOLERANCE) -> np.ndarray:
    """Return `pose` as a float64 4x4 SE(3) matrix with its rotation re-orthonormalised.

    Raises ValueError naming `name` if the pose has the wrong shape, is not finite, or is
    not a rigid transform within `tol`.
    """
    try:
        arr = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not a numeric 4x4 array ({exc})") from None
    if arr.shape != (4, 4):
        raise ValueError(f"{name}: expected shape (4, 4), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf")
    if not np.allclose(arr[3], (0.0, 0.0, 0.0, 1.0), atol=tol):
        raise ValueError(f"{name}: last row must be [0, 0, 0, 1], got {arr[3].tolist()}")
    rot = arr[:3, :3]
    ortho_err = float(np.max(np.abs(rot.T @ rot - np.eye(3))))
    if ortho_err > tol:
        raise ValueError(f"{name}: rotation is not orthonormal (max |R^T R - I| = {ortho_err:.3g})")
    det = float(np.linalg.det(rot))
    if abs(det - 1.0) > tol:
        raise ValueError(f"{name}: rotation determinant is {det:.6g}, expected +1")
    out = np.eye(4)
    out[:3, :3] = project_to_so3(rot)
    out[:3, 3] = arr[:3, 3]
    return out


def as_pose_array(name: str, poses: object, tol: float = DEFAULT_ROTATION_TOLERANCE) -> np.ndarray:
    """Validate a sequence of poses into an (N, 4, 4) float64 array."""
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not a numeric (N, 4, 4) array ({exc})") from None
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected shape (N, 4, 4), got {arr.shape}")
    if len(arr) == 0:
        return arr.reshape(0, 4, 4)
    return np.stack([as_pose(f"{name}[{k}]", p, tol) for k, p in enumerate(arr)])


def project_to_so3(rot: np.ndarray) -> np.ndarray:
    """Closest rotation matrix (SVD), so rounding noise never reaches GTSAM."""
    u, _, vt = np.linalg.svd(rot)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag((1.0, 1.0, d)) @ vt


def rot_z(yaw: float) -> np.ndarray:
    """Rotation about z by `yaw` radians."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_pose(rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """4x4 from a 3x3 rotation and a translation 3-vector."""
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = np.asarray(trans, dtype=np.float64).reshape(3)
    return out


def invert(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform without a general matrix inverse."""
    rot = pose[:3, :3]
    return make_pose(rot.T, -rot.T @ pose[:3, 3])


def relative(pose_i: np.ndarray, pose_j: np.ndarray) -> np.ndarray:
    """T_ij = inv(T_i) @ T_j: the pose of j expressed in the frame of i."""
    return invert(pose_i) @ pose_j


def rotation_angle(rot: np.ndarray) -> float:
    """Geodesic angle (rad) of a rotation matrix; atan2 keeps it accurate near 0 and pi."""
    skew = rot - rot.T
    sin = np.linalg.norm([skew[2, 1], skew[0, 2], skew[1, 0]]) / 2.0
    cos = (np.trace(rot) - 1.0) / 2.0
    return float(np.arctan2(sin, cos))


def yaw_of(rot: np.ndarray) -> float:
    """Heading (rad) of a rotation's x axis in the xy plane."""
    return float(np.arctan2(rot[1, 0], rot[0, 0]))
