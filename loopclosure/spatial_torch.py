"""Stage II on a torch device: the same scores as `loopclosure.spatial`, all candidates at once.

On a GPU, stage II of the default preset (50 candidates and the sequence terms, each a
169 x 169 x 100 product and the consistency counts) is a handful of small kernels instead of
numpy on the CPU beside the backbone. The candidates' grids go to the device as stored
(float16: half the bytes) and are widened there. Products run in full float32 (no TF32, no
reduced-precision sums, as for stage I's exact search), so the best cells match numpy's up to
the order a BLAS sums in: a candidate whose two best query cells tie to float32 rounding may
pick the other one (a count or two of its raw score); the tests bound how often.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from loopclosure.config import VPRConfig
from loopclosure.errors import LoopClosureInputError
from loopclosure.spatial import SpatialResult, check_grids, max_raw_score, spatial_scores


def spatial_scores_torch(query: np.ndarray, candidates: np.ndarray, device: str) -> SpatialResult:
    """`spatial.spatial_scores` on `device` (cuda, or cpu for the tests), in one batch."""
    import torch

    check_grids(query, candidates)
    n, gh, gw, d = candidates.shape
    if n == 0:
        return SpatialResult(np.empty(0, np.float32), np.empty(0, np.int64), np.empty((0, 2), np.int64))
    q = torch.from_numpy(np.ascontiguousarray(query, dtype=np.float32).reshape(gh * gw, d)).to(device)
    c = torch.from_numpy(np.require(candidates, requirements=["C", "W"])).to(device).float()
    raw, shifts = _consistency_counts(_best_cells(q, c), gh, gw)
    raw_np = raw.cpu().numpy()
    return SpatialResult((raw_np / max_raw_score(gh, gw)).astype(np.float32), raw_np, shifts.cpu().numpy())


def spatial_scores_torch_many(groups: list[tuple[np.ndarray, np.ndarray]], device: str) -> list[np.ndarray]:
    """The scores of `spatial_scores_torch` for several (query grid, candidate grids) groups, with
    one upload and one download for all. A sequence step scores a few places against each of its
    L-1 earlier queries: on a GPU each separate call waited for the device twice, and the waits,
    not the arithmetic, made sequence matching the slowest stage II work of a keyframe. Each
    group's product has the shape its own call has, so the scores are that call's, exactly."""
    import torch

    if not groups:
        return []
    gh, gw, d = groups[0][0].shape
    for query, candidates in groups:
        check_grids(query, candidates, (gh, gw, d))
    sizes = [len(candidates) for _, candidates in groups]
    if not sum(sizes):
        return [np.empty(0, np.float32) for _ in groups]
    queries = np.stack([np.asarray(query, np.float32).reshape(gh * gw, d) for query, _ in groups])
    stored = np.concatenate([candidates for _, candidates in groups])  # as stored (float16: half the bytes)
    q_all = torch.from_numpy(queries).to(device)
    c_all = torch.from_numpy(np.require(stored, requirements=["C", "W"])).to(device).float()
    starts = np.cumsum([0, *sizes]).tolist()
    bests = [_best_cells(q_all[g], c_all[starts[g] : starts[g + 1]]) for g, n in enumerate(sizes) if n]
    raw, _ = _consistency_counts(torch.cat(bests), gh, gw)
    scores = (raw.cpu().numpy() / max_raw_score(gh, gw)).astype(np.float32)
    return np.split(scores, starts[1:-1])


def _best_cells(q: Any, c: Any) -> Any:
    """For each cell of the (n, gh, gw, d) candidate grids `c`, the query cell of `q` (gh*gw, d)
    nearest to it (`spatial.best_query_cells`), on their device: the product in full float32."""
    from loopclosure.device_search import full_float32

    n, gh, gw, d = c.shape
    with full_float32():
        affinity = c.reshape(-1, d) @ (2.0 * q.T)
    affinity -= (q * q).sum(1)[None, :]
    return affinity.argmax(1).reshape(n, gh, gw)


def _consistency_counts(best: Any, gh: int, gw: int) -> tuple[Any, Any]:
    """`spatial.consistency_counts` in torch (the same closed form: squared group sizes per row
    and per column of each candidate's displacement codes)."""
    import torch

    n = best.shape[0]
    dev = best.device
    rows, cols = best // gw, best % gw
    d_row = rows - torch.arange(gh, device=dev)[None, :, None] + (gh - 1)
    d_col = cols - torch.arange(gw, device=dev)[None, None, :] + (gw - 1)
    n_codes = (2 * gh - 1) * (2 * gw - 1)
    code = d_row * (2 * gw - 1) + d_col
    cand = torch.arange(n, device=dev)
    row_key = (cand[:, None, None] * gh + torch.arange(gh, device=dev)[None, :, None]) * n_codes + code
    col_key = (cand[:, None, None] * gw + torch.arange(gw, device=dev)[None, None, :]) * n_codes + code
    row_counts = torch.bincount(row_key.reshape(-1), minlength=n * gh * n_codes).reshape(n, -1)
    col_counts = torch.bincount(col_key.reshape(-1), minlength=n * gw * n_codes).reshape(n, -1)
    raw = (row_counts.long() ** 2).sum(1) + (col_counts.long() ** 2).sum(1)
    totals = torch.bincount((cand[:, None, None] * n_codes + code).reshape(-1), minlength=n * n_codes)
    dominant = totals.reshape(n, n_codes).argmax(1)
    shifts = torch.stack((dominant // (2 * gw - 1), dominant % (2 * gw - 1)), dim=1)
    return raw, shifts - torch.tensor([gh - 1, gw - 1], device=dev)


def stage2_scores(query: np.ndarray, candidates: np.ndarray, vpr: VPRConfig) -> SpatialResult:
    """Stage II where `vpr.spatial.device` says: numpy on the CPU (the reference), or torch on
    the GPU (auto: where the backbone runs on one)."""
    device = _device(vpr.spatial.device, vpr.backbone.device)
    if device == "cpu":
        return spatial_scores(query, candidates, vpr.spatial.chunk_candidates)
    return spatial_scores_torch(query, candidates, device)


def stage2_scores_many(groups: list[tuple[np.ndarray, np.ndarray]], vpr: VPRConfig) -> list[np.ndarray]:
    """`stage2_scores(...).scores` of several (query, candidates) groups: on the GPU in one batch
    (`spatial_scores_torch_many`), on the CPU one group after another (nothing to wait for)."""
    device = _device(vpr.spatial.device, vpr.backbone.device)
    if device == "cpu":
        return [spatial_scores(q, c, vpr.spatial.chunk_candidates).scores for q, c in groups]
    return spatial_scores_torch_many(groups, device)


@functools.cache
def _device(spatial: str, backbone: str) -> str:
    import torch

    if spatial == "auto":  # the backbone's: cuda when it runs on a GPU
        return "cuda" if backbone in ("auto", "cuda") and torch.cuda.is_available() else "cpu"
    if spatial == "cuda" and not torch.cuda.is_available():
        raise LoopClosureInputError("vpr.spatial.device: cuda, but torch sees no CUDA device")
    return spatial
