"""Cubes and PCA where the backbone left its maps: one unfold and one product per stage.

Why: on a GPU the maps of two images are megabytes of float32 and the codes kilobytes; cutting
cubes and projecting them on the host cost most of a keyframe's backbone stage on the H200
(docs/streaming.md). `torch.nn.functional.unfold` lays a window out channel-major, then row, then
column, which is `loopclosure.cubes.extract_cubes`'s order, so the PCA rows apply unchanged.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from loopclosure.config import CubeConfig, VPRConfig, grid_side
from loopclosure.device_search import full_float32
from loopclosure.errors import LoopClosureInputError
from loopclosure.pca import Codebooks, PCAProjection

_TINY = float(np.finfo(np.float32).tiny)
_EPS = float(np.finfo(np.float32).eps)


def uses_torch_projection(config: VPRConfig, device: torch.device) -> bool:
    """`vpr.backbone.projection` resolved for a backbone on `device`."""
    if config.backbone.projection == "auto":
        return device.type == "cuda"
    return config.backbone.projection == "torch"


class _DeviceProjection:
    """One stage's PCA rows, copied to the device once."""

    def __init__(self, projection: PCAProjection, device: torch.device) -> None:
        self.dim = projection.dim
        self.mean = torch.from_numpy(projection.mean).to(device)[None, :, None]  # (1, D, 1)
        self.components = torch.from_numpy(projection.components).to(device)  # (d, D)
        self.scale = (
            torch.from_numpy(np.sqrt(np.maximum(projection.explained_variance, _EPS))).to(device)
            if projection.whiten
            else None
        )
        self.l2_normalize = projection.l2_normalize_output

    def __call__(self, cubes: torch.Tensor) -> torch.Tensor:
        """(B, D, G) cube columns -> (B, G, d) codes; the host's (x - mean) @ C.T, in that order."""
        if cubes.shape[1] != self.components.shape[1]:
            raise LoopClosureInputError(f"PCA expects vectors of {self.components.shape[1]} dims, got {cubes.shape[1]}")
        codes = torch.matmul(self.components, cubes - self.mean).transpose(1, 2).contiguous()
        if self.scale is not None:
            codes = codes / self.scale
        if self.l2_normalize:
            codes = codes / torch.linalg.vector_norm(codes, dim=-1, keepdim=True).clamp_min(_TINY)
        return codes


class TorchProjection:
    """Both stages' maps to codes on the maps' device; only the codes come back."""

    def __init__(self, config: VPRConfig, codebooks: Codebooks, device: torch.device) -> None:
        self.config = config
        self.codebooks = codebooks
        self.device = device
        self._stage1 = _DeviceProjection(codebooks.stage1, device)
        self._stage2 = _DeviceProjection(codebooks.stage2, device)

    @torch.inference_mode()
    def __call__(self, maps1: torch.Tensor, maps2: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """float32 (B, C, H, W) maps of stage I and II -> float32 numpy codes (B, n1, d1) and
        (B, gh, gw, d2), as `Encoder.project` gives them."""
        # fp32 products as the host computes them, whatever TF32 setting the process has elsewhere
        with full_float32():
            stage1 = self._stage1(_cube_columns(maps1.to(self.device), self.config.filtering.cubes))
            stage2 = self._stage2(_cube_columns(maps2.to(self.device), self.config.spatial.cubes))
        batch, _, height, width = maps2.shape
        rows, columns = (grid_side(side, self.config.spatial.cubes) for side in (height, width))
        return stage1.cpu().numpy(), stage2.reshape(batch, rows, columns, self._stage2.dim).cpu().numpy()


def _cube_columns(maps: torch.Tensor, cubes: CubeConfig) -> torch.Tensor:
    """(B, C, H, W) -> (B, C*L*L, gh*gw): extract_cubes's vectors as columns."""
    if maps.ndim != 4:
        raise ValueError(f"conv maps must be (B, C, H, W), got {tuple(maps.shape)}")
    if cubes.l2_normalize_locations:
        maps = maps / torch.linalg.vector_norm(maps, dim=1, keepdim=True).clamp_min(_TINY)
    return F.unfold(maps, kernel_size=cubes.cube_size, stride=cubes.stride)
