"""GTSAM noise models built from the config: Gaussian sigmas and robust loop kernels.

Only this module and `pose_graph` / `gnc` touch `gtsam.noiseModel`; inputs are checked here
first because GTSAM aborts or misbehaves on non-positive sigmas and non-SPD information.
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from ssmvpr_slam.backend.config import RobustKernelConfig

POSE3_DIM = 6


def sigmas6(rot_sigma: float, trans_sigma: float) -> np.ndarray:
    """Pose3 tangent sigmas (rx, ry, rz, tx, ty, tz) from one rotation and one translation sigma."""
    return np.array([rot_sigma] * 3 + [trans_sigma] * 3, dtype=np.float64)


def check_sigmas(name: str, sigmas: Sequence[float] | np.ndarray) -> np.ndarray:
    """Six finite positive sigmas, or ValueError naming `name`."""
    arr = np.asarray(sigmas, dtype=np.float64).reshape(-1)
    if arr.shape != (POSE3_DIM,):
        raise ValueError(f"{name}: expected 6 sigmas (rx, ry, rz, tx, ty, tz), got {arr.size}")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError(f"{name}: sigmas must be finite and > 0, got {arr.tolist()}")
    return arr


def check_information(name: str, information: np.ndarray) -> np.ndarray:
    """A finite symmetric positive-definite 6x6 information matrix, or ValueError."""
    arr = np.asarray(information, dtype=np.float64)
    if arr.shape != (POSE3_DIM, POSE3_DIM):
        raise ValueError(f"{name}: expected a 6x6 information matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf")
    if not np.allclose(arr, arr.T, rtol=1e-9, atol=1e-12 * max(1.0, float(np.abs(arr).max()))):
        raise ValueError(f"{name}: information matrix is not symmetric")
    if float(np.linalg.eigvalsh(arr).min()) <= 0.0:
        raise ValueError(f"{name}: information matrix is not positive definite")
    return arr


def gaussian(sigmas: np.ndarray) -> gtsam.noiseModel.Gaussian:
    """Diagonal Gaussian from already-checked sigmas."""
    return gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=np.float64))


def gaussian_from_information(information: np.ndarray) -> gtsam.noiseModel.Gaussian:
    """Full Gaussian from an already-checked information matrix."""
    return gtsam.noiseModel.Gaussian.Information(np.asarray(information, dtype=np.float64))


def make_kernel(cfg: RobustKernelConfig) -> gtsam.noiseModel.mEstimator.Base | None:
    """The configured M-estimator, or None for plain least squares."""
    est = gtsam.noiseModel.mEstimator
    factories = {
        "cauchy": est.Cauchy,
        "huber": est.Huber,
        "dcs": est.DCS,
        "geman_mcclure": est.GemanMcClure,
        "tukey": est.Tukey,
    }
    scale = cfg.resolved_scale()
    if scale is None:
        return None
    return factories[cfg.kind].Create(float(scale))  # type: ignore[attr-defined]  # gtsam's stubs lack Create


def robustify(base: gtsam.noiseModel.Base, kernel: gtsam.noiseModel.mEstimator.Base | None) -> gtsam.noiseModel.Base:
    """Wrap a Gaussian in the robust kernel (no-op for None)."""
    if kernel is None:
        return base
    return gtsam.noiseModel.Robust.Create(kernel, base)
