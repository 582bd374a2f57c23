"""Exact stage-I proposals from torch matrix products: the city-scale search for a GPU.

No exact scan of a city fits a query's budget on two CPU cores (1M places are 16M vectors:
1.3 s through faiss), and the approximate indexes buy time with recall. A GPU can scan all
of them: the database's stage-I vectors live on the device as float32, a query's vectors
are multiplied against every one, and top-k picks the proposals. As with faiss these are
float32 similarities, so every vector within the rounding margin of the k-th is proposed and
`filtering.rank_neighbours` decides on exact float64 values: the votes equal numpy brute
force, bit for bit, whatever order the device sums in. That margin holds for full float32
products only, so TF32 (GPU) and bf16 (oneDNN) products are switched off around the
product. torch keeps that setting per process: a lock keeps two searches from restoring it
under each other, and matmuls of other threads run in full float32 meanwhile (slower, never
less exact).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np

from loopclosure.config import FilteringConfig
from loopclosure.errors import LoopClosureError, LoopClosureInputError
from loopclosure.filtering import widen_until_complete

_PRECISION_LOCK = threading.Lock()
SIMILARITY_BYTES = 256 << 20  # one query's block of similarities on the device (vpr.filtering.torch_block_rows)


def resolve_device(device: str) -> str:
    """auto -> cuda when torch sees a GPU, else cpu; cuda without one is a configuration error."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise LoopClosureInputError("vpr.filtering.torch_device: cuda, but torch sees no CUDA device")
    return device


def check_search_device(filtering: FilteringConfig) -> None:
    """Refuse a torch exact search on a GPU that is not there before any work is done (a SLAM
    run would otherwise fail only once its PCA warm-up is over, a benchmark after encoding)."""
    if filtering.exact_backend == "torch" and filtering.index in ("auto", "exact"):
        resolve_device(filtering.torch_device)


@contextlib.contextmanager
def full_float32() -> Iterator[None]:
    """float32 products in full float32 for the duration, the caller's setting restored after.

    torch >= 2.9 keeps one setting per backend (reading the old global one after a backend's
    was set raises), so those are set when they exist, the global one otherwise."""
    import torch

    with _PRECISION_LOCK:
        backends = [
            b
            for b in (getattr(torch.backends.cuda, "matmul", None), getattr(torch.backends.mkldnn, "matmul", None))
            if b is not None and hasattr(b, "fp32_precision")
        ]
        if backends:
            before = [b.fp32_precision for b in backends]
            try:
                for b in backends:
                    b.fp32_precision = "ieee"
                yield
            finally:
                for b, value in zip(backends, before):
                    b.fp32_precision = value
        else:
            legacy = torch.get_float32_matmul_precision()
            torch.set_float32_matmul_precision("highest")
            try:
                yield
            finally:
                torch.set_float32_matmul_precision(legacy)


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """torch's intra-op threads for the duration (a search on the CPU, as faiss gets its own):
    with 2 shared cores, threads the backbone just used still spin and two only fight."""
    import torch

    before = torch.get_num_threads()
    if n is None or n == before:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class TorchExactSearch:
    """Every stage-I vector on one torch device; vector i is row i, written at its own offset."""

    def __init__(self, dim: int, device: str, block_rows: int | None = None, cpu_threads: int | None = None) -> None:
        self.dim = dim
        self.device = resolve_device(device)
        self.block_rows = block_rows
        self.cpu_threads = cpu_threads  # torch's threads for a search on the CPU (None: as they are)
        self._rows: Any = None  # torch (capacity, dim) float32 on the device
        self._count = 0

    def __len__(self) -> int:
        return self._count

    @property
    def on_gpu(self) -> bool:
        import torch

        return torch.device(self.device).type != "cpu"

    def reserve(self, rows: int) -> None:
        """Room for `rows` vectors: a bulk load asks once for all, appends grow by half."""
        import torch

        capacity = 0 if self._rows is None else len(self._rows)
        if rows <= capacity:
            return
        try:
            grown = torch.empty((rows, self.dim), dtype=torch.float32, device=self.device)
        except torch.cuda.OutOfMemoryError as exc:
            gb = rows * self.dim * 4 / 1e9
            raise LoopClosureError(
                f"stage-I vectors ({gb:.1f} GB float32) do not fit on {self.device}: "
                "use vpr.filtering.index ivf, or exact_backend faiss"
            ) from exc
        if self._count:
            grown[: self._count] = self._rows[: self._count]
        self._rows = grown

    def write(self, offset: int, rows: np.ndarray) -> None:
        """Vectors [offset, offset + len(rows)); what lay at or past `offset` is dropped, so a
        sync interrupted half way (out of memory, say) is redone at the right place."""
        import torch

        if not 0 <= offset <= self._count:
            raise ValueError(f"write at vector {offset}, but {self._count} are held")
        rows = np.asarray(rows, np.float32)
        if rows.ndim != 2 or rows.shape[1] != self.dim:
            raise ValueError(f"stage-I rows must be (m, {self.dim}), got {rows.shape}")
        if not rows.flags.writeable or not rows.flags.c_contiguous:  # a read-only memory-mapped map
            rows = np.array(rows, np.float32, order="C")
        stop = offset + len(rows)
        capacity = 0 if self._rows is None else len(self._rows)
        if stop > capacity:
            self.reserve(max(stop, capacity + capacity // 2, 1024))
        self._count = offset
        self._rows[offset:stop] = torch.from_numpy(rows).to(self.device)
        self._count = stop

    def propose(
        self, query: np.ndarray, k: int, limit: int, excluded_ids: np.ndarray, margin: np.ndarray
    ) -> list[np.ndarray]:
        """Per query row, ascending ids among the first `limit` vectors (less `excluded_ids`) of
        every vector whose float32 similarity lies within `margin[row]` of the k-th largest: a
        superset of the exact top k."""
        import torch

        threads = self.cpu_threads if not self.on_gpu else None
        with full_float32(), torch_threads(threads), torch.inference_mode():
            q = torch.from_numpy(np.ascontiguousarray(query, np.float32)).to(self.device)
            excluded = np.sort(np.asarray(excluded_ids, np.int64))
            block = self.block_rows or max(1, SIMILARITY_BYTES // (4 * max(1, len(query))))
            held = self._similarities(q, 0, limit, excluded) if limit <= block else None

            def fetch(todo: np.ndarray, kk: int) -> zip[tuple[np.ndarray, np.ndarray]]:
                every = len(todo) == len(query)
                if held is not None:  # the whole map in one block: multiplied once, widening reuses it
                    sims = held if every else held[torch.from_numpy(todo).to(self.device)]
                    top = torch.topk(sims, kk, dim=1, sorted=True)
                    values, ids = top.values, top.indices
                else:  # widening multiplies the blocks again, for the rows still unsettled only
                    rows = q if every else q[torch.from_numpy(todo).to(self.device)]
                    values, ids = self._top_by_blocks(rows, kk, limit, excluded, block)
                # kk <= allowed: no excluded -inf among the kk kept
                return zip(values.cpu().numpy(), ids.cpu().numpy())

            return widen_until_complete(len(query), k, limit - len(excluded), margin, fetch)

    def _similarities(self, q: Any, start: int, stop: int, excluded: np.ndarray) -> Any:
        """q against vectors [start, stop), the excluded ones at -inf."""
        import torch

        sims = q @ self._rows[start:stop].T
        inside = excluded[(excluded >= start) & (excluded < stop)] - start
        if len(inside):
            sims[:, torch.from_numpy(inside).to(self.device)] = -torch.inf
        return sims

    def _top_by_blocks(self, q: Any, kk: int, limit: int, excluded: np.ndarray, block: int) -> tuple[Any, Any]:
        """The kk largest similarities of each row over all blocks: each block's own kk largest,
        merged into the running best (a block's -inf only survive while the map has fewer). The
        merge holds 2 kk per row; kk is k plus slack unless mass ties make the widening double it."""
        import torch

        values: Any = None
        ids: Any = None
        for start in range(0, limit, block):
            stop = min(limit, start + block)
            top = torch.topk(self._similarities(q, start, stop, excluded), min(kk, stop - start), dim=1, sorted=False)
            block_ids = top.indices + start
            if values is None:
                values, ids = top.values, block_ids
            else:
                values, ids = torch.cat([values, top.values], dim=1), torch.cat([ids, block_ids], dim=1)
            if values.shape[1] > kk:
                best = torch.topk(values, kk, dim=1, sorted=False)
                values, ids = best.values, torch.gather(ids, 1, best.indices)
        order = torch.argsort(values, dim=1, descending=True)
        return torch.gather(values, 1, order), torch.gather(ids, 1, order)
