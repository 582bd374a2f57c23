"""Umeyama least-squares alignment of point sets / trajectories (SE(3) or Sim(3)).

Umeyama (1991): find s, R, t minimising sum |target_k - (s R source_k + t)|^2. Used to put an
estimated trajectory into the ground-truth frame before ATE, as evo's ``align`` does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_POINTS = 3
"""Fewer correspondences leave the rotation undetermined."""


@dataclass(frozen=True)
class Alignment:
    """target ≈ scale * rotation @ source + translation."""

    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0

    def apply_points(self, points: np.ndarray) -> np.ndarray:
        """Transform (N, 3) points."""
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation

    def apply_poses(self, poses: np.ndarray) -> np.ndarray:
        """Transform (N, 4, 4) poses: rotations are rotated, positions scaled and moved."""
        poses = np.asarray(poses, dtype=np.float64)
        out = poses.copy()
        out[:, :3, :3] = self.rotation @ poses[:, :3, :3]
        out[:, :3, 3] = self.apply_points(poses[:, :3, 3])
        return out

    def as_matrix(self) -> np.ndarray:
        """4x4 similarity matrix [sR t; 0 1]."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out

    def to_dict(self) -> dict[str, object]:
        return {
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "scale": float(self.scale),
        }


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = False) -> Alignment:
    """Least-squares similarity (or rigid, `with_scale=False`) from `source` onto `target`."""
    src = _points("source", source)
    dst = _points("target", target)
    if src.shape != dst.shape:
        raise ValueError(f"source, target: shapes differ, {src.shape} vs {dst.shape}")
    if len(src) < MIN_POINTS:
        raise ValueError(f"source: need at least {MIN_POINTS} points to align, got {len(src)}")
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    cov = dst_c.T @ src_c / len(src)
    u, sing, vt = np.linalg.svd(cov)
    reflect = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        reflect[2, 2] = -1.0
    rot = u @ reflect @ vt
    scale = 1.0
    if with_scale:
        var_src = float(np.mean(np.sum(src_c**2, axis=1)))
        if var_src == 0.0:
            raise ValueError("source: all points coincide, scale is undefined")
        scale = float(np.trace(np.diag(sing) @ reflect) / var_src)
    trans = mu_dst - scale * rot @ mu_src
    return Alignment(rot, trans, scale)


def align_trajectory(
    est_poses: np.ndarray, ref_poses: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, Alignment]:
    """Align estimated poses onto reference poses by their positions; returns (aligned, T)."""
    est = np.asarray(est_poses, dtype=np.float64)
    ref = np.asarray(ref_poses, dtype=np.float64)
    alignment = umeyama(est[:, :3, 3], ref[:, :3, 3], with_scale)
    return alignment.apply_poses(est), alignment


def _points(name: str, points: np.ndarray) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf")
    return arr
