"""Exact stage-I proposals from torch matrix products: the city-scale search for a GPU.

No exact scan of a city fits a query's budget on two CPU cores (1M places are 16M vectors:
1.3 s through faiss), and the approximate indexes buy time with recall. A GPU can scan all
of them: the database's stage-I vectors live on the device as float32, a query's vectors
are multiplied against every one, and top-k picks the proposals. As with faiss these are
float32 similarities, so every vector within the rounding margin of the k-th is proposed and
`filtering.rank_neighbours` decides on exact float64 values: the votes equal numpy brute
force, bit for bit, whatever order the device sums in. TF32 is switched off for the product,
since its 10-bit mantissa would break that margin.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np

from loopclosure.errors import LoopClosureInputError


def resolve_device(device: str) -> str:
    """auto -> cuda when torch sees a GPU, else cpu; cuda without one is a configuration error."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise LoopClosureInputError("vpr.filtering.torch_device: cuda, but torch sees no CUDA device")
    return device


@contextlib.contextmanager
def _full_float32() -> Iterator[None]:
    """float32 products in full float32 (no TF32 on a GPU, no bf16 on a CPU) for one call."""
    import torch

    before = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("highest")
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(before)


class TorchExactSearch:
    """Every stage-I vector on one torch device, grown by doubling as places are added."""

    def __init__(self, dim: int, device: str) -> None:
        self.dim = dim
        self.device = resolve_device(device)
        self._rows: Any = None  # torch (capacity, dim) float32 on the device
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def append(self, rows: np.ndarray) -> None:
        import torch

        rows = np.ascontiguousarray(rows, np.float32)
        if rows.ndim != 2 or rows.shape[1] != self.dim:
            raise ValueError(f"stage-I rows must be (m, {self.dim}), got {rows.shape}")
        needed = self._count + len(rows)
        if self._rows is None or len(self._rows) < needed:
            capacity = max(needed, 2 * (0 if self._rows is None else len(self._rows)), 1024)
            grown = torch.empty((capacity, self.dim), dtype=torch.float32, device=self.device)
            if self._count:
                grown[: self._count] = self._rows[: self._count]
            self._rows = grown
        self._rows[self._count : needed] = torch.from_numpy(rows).to(self.device)
        self._count = needed

    def propose(
        self, query: np.ndarray, k: int, limit: int, excluded_ids: np.ndarray, margin: np.ndarray
    ) -> list[np.ndarray]:
        """Per query row, ascending ids among the first `limit` vectors (less `excluded_ids`) of
        every vector whose float32 similarity lies within `margin[row]` of the k-th largest: a
        superset of the exact top k."""
        import torch

        n_allowed = limit - len(excluded_ids)
        with _full_float32(), torch.inference_mode():
            q = torch.from_numpy(np.ascontiguousarray(query, np.float32)).to(self.device)
            sims = q @ self._rows[:limit].T  # (n, limit)
            if len(excluded_ids):
                sims[:, torch.from_numpy(np.asarray(excluded_ids, np.int64)).to(self.device)] = -torch.inf
            out: list[np.ndarray | None] = [None] * len(query)
            todo = np.arange(len(query))
            kk = min(k + max(8, k // 4), n_allowed)
            while len(todo):
                top = torch.topk(sims[torch.from_numpy(todo).to(self.device)], kk, dim=1, sorted=True)
                values, ids = top.values.cpu().numpy().astype(np.float64), top.indices.cpu().numpy()
                again = []
                for row, s, i in zip(todo, values, ids):
                    floor = s[k - 1] - margin[row]
                    # complete: nothing left out can be within the margin of the k-th
                    if kk >= n_allowed or s[-1] < floor:
                        out[row] = np.sort(i[s >= floor])
                    else:
                        again.append(row)
                todo, kk = np.asarray(again, np.int64), min(2 * kk, n_allowed)
        return out  # type: ignore[return-value]
