"""Exact stage-I proposals from torch matrix products: the city-scale search for a GPU.

No exact scan of a city fits a query's budget on two CPU cores (1M places are 16M vectors:
1.3 s through faiss), and the approximate indexes buy time with recall. A GPU can scan all
of them: the database's stage-I vectors live on the device, a query's vectors are
multiplied against every one, and the largest products are the proposals. As with faiss
these are rounded similarities, so every vector within the rounding margin of the k-th is
proposed and `filtering.rank_neighbours` decides on exact float64 values: the votes equal
numpy brute force, bit for bit, whatever order the device sums in.

On a GPU the copy is float16 (`torch_storage: auto`): a scan of 1M places reads half the
bytes, and the margin grows by what rounding the vectors and the query to float16 can move
a product (about 2^-11 of |q| max|x|), so the proposals still hold the exact top k. The
products accumulate in float32 either way; the margin holds for that only, so TF32 (GPU)
and bf16 (oneDNN) float32 products are switched off around the product. torch keeps that
setting per process: a lock keeps two searches from restoring it under each other, and
matmuls of other threads run in full float32 meanwhile (slower, never less exact).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np

from loopclosure.config import FilteringConfig
from loopclosure.errors import LoopClosureError, LoopClosureInputError
from loopclosure.filtering import F32_UNIT_ROUNDOFF, similarity_margin, widen_until_complete

_PRECISION_LOCK = threading.Lock()
SIMILARITY_BYTES = 256 << 20  # one query's block of similarities on the CPU (vpr.filtering.torch_block_rows)
GPU_SIMILARITY_BYTES = 1 << 30  # on a GPU, at most 1/64 of its memory: a 1M-place map in one block
FLOAT16_LIMIT = 60_000.0  # stage-I values a float16 copy takes (its largest finite value is 65504)
_F16_UNIT_ROUNDOFF = 2.0**-11
_F16_SUBNORMAL_ERROR = 2.0**-25  # half the spacing of float16's subnormals: the rounding error near 0
SELECT_CHUNK = 4096  # columns per chunk whose maximum bounds a row's k-th largest (top_k_columns)


def resolve_device(device: str) -> str:
    """auto -> cuda when torch sees a GPU, else cpu; cuda without one is a configuration error."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise LoopClosureInputError("vpr.filtering.torch_device: cuda, but torch sees no CUDA device")
    return device


def resolve_backend(filtering: FilteringConfig) -> str:
    """auto -> torch where torch sees a GPU it may use (torch_device auto or cuda): a GPU scans a
    city exactly in milliseconds; faiss otherwise, as fast as torch on the CPU."""
    if filtering.exact_backend != "auto":
        return filtering.exact_backend
    import torch

    return "torch" if filtering.torch_device != "cpu" and torch.cuda.is_available() else "faiss"


def check_search_device(filtering: FilteringConfig) -> None:
    """Refuse a torch exact search on a GPU that is not there before any work is done (a SLAM
    run would otherwise fail only once its PCA warm-up is over, a benchmark after encoding)."""
    if resolve_backend(filtering) == "torch" and filtering.index in ("auto", "exact"):
        resolve_device(filtering.torch_device)


@contextlib.contextmanager
def full_float32() -> Iterator[None]:
    """float32 products in full float32 for the duration, the caller's setting restored after.

    torch >= 2.9 keeps one setting per backend (reading the old global one after a backend's
    was set raises), so those are set when they exist, the global one otherwise."""
    import torch

    with _PRECISION_LOCK, _no_reduced_precision_reductions():
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
def _no_reduced_precision_reductions() -> Iterator[None]:
    """cuBLAS may sum float16 products in float16 unless told not to: the margin assumes float32."""
    import torch

    matmul = torch.backends.cuda.matmul
    names = [n for n in ("allow_fp16_reduced_precision_reduction", "allow_bf16_reduced_precision_reduction")
             if hasattr(matmul, n)]  # fmt: skip
    before = [getattr(matmul, n) for n in names]
    try:
        for n in names:
            setattr(matmul, n, False)
        yield
    finally:
        for n, value in zip(names, before):
            setattr(matmul, n, value)


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


def resolve_storage(storage: str, on_gpu: bool) -> str:
    """auto -> float16 on a GPU (a scan reads half the bytes), float32 on the CPU (whose
    float16 products are slow)."""
    return ("float16" if on_gpu else "float32") if storage == "auto" else storage


class TorchExactSearch:
    """Every stage-I vector on one torch device; vector i is row i, written at its own offset."""

    def __init__(
        self,
        dim: int,
        device: str,
        block_rows: int | None = None,
        cpu_threads: int | None = None,
        storage: str = "auto",
    ) -> None:
        self.dim = dim
        self.device = resolve_device(device)
        self.block_rows = block_rows
        self.cpu_threads = cpu_threads  # torch's threads for a search on the CPU (None: as they are)
        self.storage = resolve_storage(storage, self.on_gpu)
        # float16 rows padded to a multiple of 8 values: the width tensor-core products want
        self._width = -(-dim // 8) * 8 if self.storage == "float16" else dim
        self._rows: Any = None  # torch (capacity, width) on the device
        self._count = 0

    def __len__(self) -> int:
        return self._count

    @property
    def on_gpu(self) -> bool:
        import torch

        return torch.device(self.device).type != "cpu"

    def _dtype(self) -> Any:
        import torch

        return torch.float16 if self.storage == "float16" else torch.float32

    def reserve(self, rows: int) -> None:
        """Room for `rows` vectors: a bulk load asks once for all, appends grow by half."""
        import torch

        capacity = 0 if self._rows is None else len(self._rows)
        if rows <= capacity:
            return
        try:
            grown = torch.zeros((rows, self._width), dtype=self._dtype(), device=self.device)
        except torch.cuda.OutOfMemoryError as exc:
            gb = rows * self._width * (2 if self.storage == "float16" else 4) / 1e9
            raise LoopClosureError(
                f"stage-I vectors ({gb:.1f} GB {self.storage}) do not fit on {self.device}: "
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
        wide = torch.from_numpy(rows).to(self.device)
        if len(rows):  # checked on the device (one pass there, none on the host), before anything changes
            if not bool(torch.isfinite(wide).all()):
                raise LoopClosureInputError(f"stage-I vectors {offset}..{offset + len(rows) - 1} hold NaN or inf")
            if self.storage == "float16" and float(wide.abs().max()) > FLOAT16_LIMIT:
                raise LoopClosureInputError(_too_large("stage-I values"))
        stop = offset + len(rows)
        capacity = 0 if self._rows is None else len(self._rows)
        if stop > capacity:
            self.reserve(max(stop, capacity + capacity // 2, 1024))
        self._count = offset
        self._rows[offset:stop, : self.dim] = wide.to(self._dtype())
        self._count = stop

    def storage_margin(self, query: np.ndarray, max_norm: float) -> np.ndarray:
        """(n,) what rounding to float16 can add to the gap between a computed and an exact
        similarity, doubled (both the k-th and a candidate move); 0 for float32 storage.
        `max_norm` bounds the stored vectors' norms.

        |q.x - q16.x16| <= |q| |x - x16| + |q - q16| |x16|, with |x - x16| <= 2^-11 |x| + 2^-25 sqrt(d)
        per vector (torch and numpy round to nearest; 2^-25 where float16 is subnormal) and
        |q - q16| measured. Tensor cores may truncate their float32 sums instead of rounding
        them, up to twice the error `similarity_margin` allows per addition: their whole sum
        bound, gamma_w(2u) |q16| |x16|, is added as well."""
        if self.storage != "float16":
            return np.zeros(len(query))
        q = np.asarray(query, np.float64)
        q16 = np.asarray(query, np.float32).astype(np.float16).astype(np.float64)
        subnormal = _F16_SUBNORMAL_ERROR * np.sqrt(self.dim)
        x_error = _F16_UNIT_ROUNDOFF * max_norm + subnormal
        x16_norm = max_norm + x_error
        q_norm, q16_norm = np.linalg.norm(q, axis=1), np.linalg.norm(q16, axis=1)
        bound = q_norm * x_error + np.linalg.norm(q - q16, axis=1) * x16_norm
        u = 2.0 * F32_UNIT_ROUNDOFF  # a truncating sum's error per addition
        bound += self._width * u / (1.0 - self._width * u) * q16_norm * x16_norm
        return 2.0 * bound

    def propose(
        self, query: np.ndarray, k: int, limit: int, excluded_ids: np.ndarray, max_norm: float
    ) -> list[np.ndarray]:
        """Per query row, ascending ids among the first `limit` vectors (less `excluded_ids`) of
        every vector whose computed similarity lies within the rounding margin of the k-th
        largest (the float32 product's, plus the float16 copy's; `max_norm` bounds the stored
        vectors' norms): a superset of the exact top k."""
        import torch

        threads = self.cpu_threads if not self.on_gpu else None
        if not np.isfinite(query).all():
            raise LoopClosureInputError("a stage-I query holds NaN or inf")
        if self.storage == "float16" and np.abs(query).max(initial=0.0) > FLOAT16_LIMIT:
            raise LoopClosureInputError(_too_large("stage-I query values"))
        margin = similarity_margin(query, max_norm) + self.storage_margin(query, max_norm)
        with full_float32(), torch_threads(threads), torch.inference_mode():
            padded = np.zeros((len(query), self._width), np.float32)
            padded[:, : self.dim] = query
            q = torch.from_numpy(padded).to(self.device).to(self._dtype())
            excluded = np.sort(np.asarray(excluded_ids, np.int64))
            block = self.block_rows or max(1, self._similarity_bytes() // (4 * max(1, len(query))))
            held = self._similarities(q, 0, limit, excluded) if limit <= block else None

            def fetch(todo: np.ndarray, kk: int) -> zip[tuple[np.ndarray, np.ndarray]]:
                every = len(todo) == len(query)
                if held is not None:  # the whole map in one block: multiplied once, widening reuses it
                    values, ids = _descending(*top_k_columns(held, kk))  # all rows: no copy of a subset
                    if not every:
                        pick = torch.from_numpy(todo).to(self.device)
                        values, ids = values[pick], ids[pick]
                else:  # widening multiplies the blocks again, for the rows still unsettled only
                    rows = q if every else q[torch.from_numpy(todo).to(self.device)]
                    values, ids = self._top_by_blocks(rows, kk, limit, excluded, block)
                # kk <= allowed: no excluded -inf among the kk kept
                return zip(values.cpu().numpy(), ids.cpu().numpy())

            # a GPU selects the top 2k as fast as the top k + slack, and a second pass costs a scan
            first = 2 * k if self.on_gpu else None
            return widen_until_complete(len(query), k, limit - len(excluded), margin, fetch, first)

    def _similarity_bytes(self) -> int:
        """A query's similarities held at once: a 1M-place map in one block on a large GPU."""
        import torch

        if torch.device(self.device).type != "cuda":
            return SIMILARITY_BYTES
        total = torch.cuda.get_device_properties(torch.device(self.device)).total_memory
        return max(SIMILARITY_BYTES, min(GPU_SIMILARITY_BYTES, total // 64))

    def _similarities(self, q: Any, start: int, stop: int, excluded: np.ndarray) -> Any:
        """float32 similarities of q with vectors [start, stop), the excluded ones at -inf."""
        import torch

        sims = _float32_product(q, self._rows[start:stop])
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
            top_values, top_ids = top_k_columns(self._similarities(q, start, stop, excluded), kk)
            block_ids = top_ids + start
            if values is None:
                values, ids = top_values, block_ids
            else:
                values, ids = torch.cat([values, top_values], dim=1), torch.cat([ids, block_ids], dim=1)
            if values.shape[1] > kk:
                best = torch.topk(values, kk, dim=1, sorted=False)
                values, ids = best.values, torch.gather(ids, 1, best.indices)
        return _descending(values, ids)


def _too_large(what: str) -> str:
    return (
        f"{what} beyond ±{FLOAT16_LIMIT:g} do not fit the GPU's float16 copy: set vpr.filtering.torch_storage: float32"
    )


def _float32_product(q: Any, rows: Any) -> Any:
    """q @ rows.T summed and returned in float32, float16 operands too (products of float16
    values are exact in float32). Where torch has no float16 product into float32 (the CPU,
    torch < 2.8), the operands are widened first: the same values, more bytes read."""
    import torch

    if q.dtype == torch.float32:
        return q @ rows.T
    if q.device.type != "cpu":
        try:
            return torch.mm(q, rows.T, out_dtype=torch.float32)
        except (TypeError, NotImplementedError):  # no such product here; out of memory is raised
            pass
    return q.float() @ rows.float().T


def _descending(values: Any, ids: Any) -> tuple[Any, Any]:
    """Each row's values from the largest, their ids alongside."""
    import torch

    order = torch.argsort(values, dim=1, descending=True)
    return torch.gather(values, 1, order), torch.gather(ids, 1, order)


def top_k_columns(sims: Any, kk: int, chunk: int = 0, select: bool | None = None) -> tuple[Any, Any]:
    """Each row's min(kk, columns) largest values and their column ids, unordered.

    On a GPU a query's 16 rows of 16M similarities make torch.topk slow (3 ms on an H200). So
    the rows are cut into chunks: kk chunks have maxima >= the kk-th largest chunk maximum t,
    so at least kk values are >= t and every one of the kk largest is. The few values >= t are
    gathered and the top kk taken among them: the values topk gives. Ties at t (a map of copies)
    can select most of a row; then, and on the CPU, it is torch.topk (`select`: None picks by
    device, True/False force the selection or topk)."""
    import torch

    chunk = chunk or SELECT_CHUNK
    n_rows, n = sims.shape
    n_chunks = n // chunk
    if select is None:
        select = sims.device.type != "cpu"
    if not select or n_chunks < max(kk, 8):
        top = torch.topk(sims, min(kk, n), dim=1, sorted=False)
        return top.values, top.indices
    whole = torch.as_strided(sims, (n_rows, n_chunks, chunk), (sims.stride(0), chunk * sims.stride(1), sims.stride(1)))
    floor = torch.topk(whole.amax(dim=2), kk, dim=1, sorted=False).values.amin(dim=1, keepdim=True)
    above = sims >= floor
    counts = above.sum(dim=1)
    widest = int(counts.max())
    if widest > n // 4:  # before the gather, which would hold 16 bytes a hit
        top = torch.topk(sims, kk, dim=1, sorted=False)
        return top.values, top.indices
    hits = above.nonzero()  # (row, column) in row order
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.arange(len(hits), device=sims.device) - starts[hits[:, 0]]
    values = torch.full((n_rows, widest), -torch.inf, dtype=sims.dtype, device=sims.device)
    ids = torch.zeros((n_rows, widest), dtype=torch.int64, device=sims.device)
    values[hits[:, 0], slot] = sims[hits[:, 0], hits[:, 1]]
    ids[hits[:, 0], slot] = hits[:, 1]
    best = torch.topk(values, kk, dim=1, sorted=False)
    return best.values, torch.gather(ids, 1, best.indices)
