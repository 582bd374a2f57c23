"""TUM and KITTI trajectory files, and the pose conversions they need.

TUM: ``t x y z qx qy qz qw`` per line (``#`` comments allowed); KITTI: the 12 values of the
top 3x4 block of a 4x4 pose, row-major. Poses are 4x4 float64. Every reading error is a
:class:`~frontend.errors.FrontendInputError` naming the file and line, because a silently
skipped or mis-parsed pose corrupts every metric computed from the trajectory later. Writes
are atomic (temp file + ``os.replace``) so a crash never leaves half a trajectory behind.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from frontend.config import PoseFileConfig
from frontend.errors import FrontendInputError

TUM_COLUMNS = 8
KITTI_COLUMNS = 12
PoseFormat = Literal["tum", "kitti"]


@dataclass
class PoseFile:
    """What a pose file held: timestamps exist for TUM only."""

    poses: np.ndarray  # (N, 4, 4)
    timestamps: np.ndarray | None  # (N,) seconds
    format: PoseFormat


# --------------------------------------------------------------------------- conversions


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion given as (qx, qy, qz, qw)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """(qx, qy, qz, qw) of a rotation matrix, with qw >= 0 (Shepperd's method)."""
    r = np.asarray(rotation, dtype=np.float64)
    trace = np.trace(r)
    diag = np.diag(r)
    # Pivot on the largest of (w, x, y, z) for numerical stability.
    k = int(np.argmax([trace, *diag]))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 - r[0, 0] + r[1, 1] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 - r[0, 0] - r[1, 1] + r[2, 2])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    quat = np.array(q)
    quat /= np.linalg.norm(quat)
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


# --------------------------------------------------------------------------- reading


def data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of each data line: blank and ``#`` lines skipped, ``,`` or
    white space between values."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise FrontendInputError(f"{path}: cannot read pose file ({error})") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            rows.append((lineno, stripped.replace(",", " ").split()))
    return rows


def _floats(path: Path, lineno: int, tokens: list[str], expected: int, what: str) -> np.ndarray:
    if len(tokens) != expected:
        raise FrontendInputError(f"{path}:{lineno}: expected {expected} values ({what}), got {len(tokens)}")
    try:
        values = np.array([float(token) for token in tokens])
    except ValueError:
        raise FrontendInputError(f"{path}:{lineno}: non-numeric value in {what}") from None
    if not np.all(np.isfinite(values)):
        raise FrontendInputError(f"{path}:{lineno}: NaN or inf in {what}")
    return values


def read_tum(path: str | Path, config: PoseFileConfig | None = None) -> PoseFile:
    """Read a TUM trajectory; quaternions must be unit length within tolerance."""
    path, config = Path(path), config or PoseFileConfig()
    stamps, poses = [], []
    for lineno, tokens in data_lines(path):
        values = _floats(path, lineno, tokens, TUM_COLUMNS, "t x y z qx qy qz qw")
        problem = quaternion_problem(values[4:], config.rotation_tolerance)
        if problem is not None:
            raise FrontendInputError(f"{path}:{lineno}: {problem}")
        stamps.append(values[0])
        poses.append(pose_from_translation_quaternion(values[1:4], values[4:]))
    return PoseFile(stack_poses(poses), np.array(stamps, dtype=np.float64), "tum")


def read_kitti(path: str | Path, config: PoseFileConfig | None = None) -> PoseFile:
    """Read a KITTI trajectory; rotations must be orthonormal within tolerance."""
    path, config = Path(path), config or PoseFileConfig()
    poses = []
    for lineno, tokens in data_lines(path):
        values = _floats(path, lineno, tokens, KITTI_COLUMNS, "3x4 row-major pose")
        pose = pose_from_kitti_row(values)
        problem = pose_problem(pose, config.rotation_tolerance)
        if problem is not None:
            raise FrontendInputError(f"{path}:{lineno}: {problem}")
        pose[:3, :3] = nearest_rotation(pose[:3, :3])
        poses.append(pose)
    return PoseFile(stack_poses(poses), None, "kitti")


def detect_format(path: str | Path) -> PoseFormat:
    """TUM or KITTI, from the number of values on the first data line."""
    path = Path(path)
    rows = data_lines(path)
    if not rows:
        raise FrontendInputError(f"{path}: pose file has no data lines")
    lineno, tokens = rows[0]
    if len(tokens) == TUM_COLUMNS:
        return "tum"
    if len(tokens) == KITTI_COLUMNS:
        return "kitti"
    raise FrontendInputError(f"{path}:{lineno}: {len(tokens)} values; expected 8 (TUM) or 12 (KITTI)")


def read_poses(path: str | Path, format: PoseFormat | None = None, config: PoseFileConfig | None = None) -> PoseFile:
    """Read a TUM or KITTI file; the format is detected when not given."""
    format = format or detect_format(path)
    return read_tum(path, config) if format == "tum" else read_kitti(path, config)


def stack_poses(poses: list[np.ndarray]) -> np.ndarray:
    """(N, 4, 4) array of a list of poses; (0, 4, 4) when empty."""
    return np.stack(poses) if poses else np.zeros((0, 4, 4))


# --------------------------------------------------------------------------- writing


def default_file_mode() -> int:
    """Permissions a plain ``open(..., "w")`` would give (mkstemp files are owner-only)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` via a temp file in the same folder and ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp, default_file_mode())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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


def _checked_poses(path: Path, poses: np.ndarray, config: PoseFileConfig) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise FrontendInputError(f"{path}: poses to write have shape {poses.shape}, need (N,4,4)")
    for index, pose in enumerate(poses):
        problem = pose_problem(pose, config.rotation_tolerance)
        if problem is not None:
            raise FrontendInputError(f"{path}: pose {index} not written: {problem}")
    return poses


def write_tum(
    path: str | Path,
    timestamps: np.ndarray,
    poses: np.ndarray,
    config: PoseFileConfig | None = None,
) -> None:
    """Write a TUM trajectory (atomically)."""
    path, config = Path(path), config or PoseFileConfig()
    poses = _checked_poses(path, poses, config)
    timestamps = np.asarray(timestamps, dtype=np.float64).ravel()
    if len(timestamps) != len(poses) or not np.all(np.isfinite(timestamps)):
        raise FrontendInputError(f"{path}: need {len(poses)} finite timestamps, got {len(timestamps)}")
    stamp_format = f"{{:.{config.timestamp_decimals}f}}"
    lines = tum_lines(timestamps, poses, stamp_format, f"{{:.{config.value_digits}g}}")
    atomic_write_text(path, "".join(line + "\n" for line in lines))


def write_kitti(path: str | Path, poses: np.ndarray, config: PoseFileConfig | None = None) -> None:
    """Write a KITTI trajectory (atomically)."""
    path, config = Path(path), config or PoseFileConfig()
    poses = _checked_poses(path, poses, config)
    lines = kitti_lines(poses, f"{{:.{config.value_digits}g}}")
    atomic_write_text(path, "".join(line + "\n" for line in lines))
