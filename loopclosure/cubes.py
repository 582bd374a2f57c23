"""Feature cubes: LxLxC windows of a conv map, flattened; the unit SSM-VPR encodes."""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from loopclosure.config import CubeConfig


def extract_cubes(maps: np.ndarray, cubes: CubeConfig) -> np.ndarray:
    """(B, C, H, W) conv maps -> (B, gh, gw, C*L*L) cube vectors on a strided grid.

    Each location's C-vector is L2-normalised first so that no single strongly activated
    location dominates a cube (the paper's normalisation).
    """
    if maps.ndim != 4:
        raise ValueError(f"conv maps must be (B, C, H, W), got {maps.shape}")
    x = maps.astype(np.float32, copy=False)
    if cubes.l2_normalize_locations:
        norm = np.linalg.norm(x, axis=1, keepdims=True)
        x = x / np.maximum(norm, np.finfo(np.float32).tiny)
    size, stride = cubes.cube_size, cubes.stride
    windows = sliding_window_view(x, (size, size), axis=(2, 3))[:, :, ::stride, ::stride]
    b, c, gh, gw = windows.shape[:4]
    return np.ascontiguousarray(windows.transpose(0, 2, 3, 1, 4, 5)).reshape(b, gh, gw, c * size * size)
