"""TUM and KITTI trajectory lines and the pose conversions they need: the file formats
themselves, shared by the readers and writers of all three packages.

TUM: ``t x y z qx qy qz qw`` per line (Hamilton quaternion, scalar last); KITTI: the 12
row-major values of the top 3x4 block of a 4x4 pose. ``#`` lines and blank lines are comments.
Poses are 4x4 float64 body-to-world. Reading the file, and the error a caller raises for a bad
line, stay with the caller: each package names its inputs in its own error class.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

TUM_COLUMNS = 8
KITTI_COLUMNS = 12


def data_lines(text: str) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of each data line of a pose file's text: blank and ``#`` lines
    skipped, ``,`` or white space between values."""
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            rows.append((lineno, stripped.replace(",", " ").split()))
    return rows


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion given as (qx, qy, qz, qw), normalised first."""
    return Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """(qx, qy, qz, qw) of a rotation matrix, with qw >= 0 (one sign for one rotation)."""
    quat = Rotation.from_matrix(np.asarray(rotation, dtype=np.float64)).as_quat()
    return -quat if quat[3] < 0 else quat


def pose_from_translation_quaternion(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """4x4 pose from a translation (x, y, z) and a quaternion (qx, qy, qz, qw)."""
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(q)
    pose[:3, 3] = t
    return pose


def nearest_rotation(rotation: np.ndarray) -> np.ndarray:
    """Closest proper rotation (SVD projection); removes rounding from text files."""
    u, _, vt = np.linalg.svd(rotation)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def pose_problem(pose: np.ndarray, tolerance: float) -> str | None:
    """Why ``pose`` is not a valid rigid transform, or None when it is."""
    pose = np.asarray(pose)
    if pose.shape != (4, 4):
        return f"pose has shape {pose.shape}, expected (4, 4)"
    if not np.all(np.isfinite(pose)):
        return "pose contains NaN or inf"
    rotation = pose[:3, :3]
    error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if error > tolerance:
        return f"rotation is not orthonormal (|R^T R - I| = {error:.3g})"
    if np.linalg.det(rotation) <= 0:
        return "rotation has a non-positive determinant (a reflection)"
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0]):
        return f"last row is {pose[3].tolist()}, expected [0, 0, 0, 1]"
    return None


def quaternion_problem(q: np.ndarray, tolerance: float) -> str | None:
    """Why ``q`` (qx, qy, qz, qw) is not a unit quaternion within ``tolerance``, or None."""
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > tolerance:
        return f"quaternion norm {norm:.6g} is not 1 (not a rotation)"
    return None


def pose_from_kitti_row(values: np.ndarray) -> np.ndarray:
    """4x4 pose from the 12 row-major values of its top 3x4 block (unchecked)."""
    pose = np.eye(4)
    pose[:3, :4] = np.reshape(values, (3, 4))
    return pose


def stack_poses(poses: list[np.ndarray]) -> np.ndarray:
    """(N, 4, 4) array of a list of poses; (0, 4, 4) when empty."""
    return np.stack(poses) if poses else np.zeros((0, 4, 4))


def tum_lines(timestamps: np.ndarray, poses: np.ndarray, stamp_format: str, value_format: str) -> list[str]:
    """``t x y z qx qy qz qw`` per pose (qw >= 0), numbers formatted with ``str.format``."""
    lines = []
    for stamp, pose in zip(timestamps, poses):
        values = [*pose[:3, 3], *matrix_to_quaternion(pose[:3, :3])]
        lines.append(" ".join([stamp_format.format(stamp), *map(value_format.format, values)]))
    return lines


def kitti_lines(poses: np.ndarray, value_format: str) -> list[str]:
    """The 12 row-major values of each pose's top 3x4 block, one pose per line."""
    return [" ".join(map(value_format.format, pose[:3, :4].ravel())) for pose in poses]
