"""Stage-I nearest-vector search through faiss, kept in step with a growing place database.

The index only proposes neighbours; `filtering.rank_neighbours` re-scores the proposals
exactly and votes. Modes (`vpr.filtering.index`):

- exact: faiss's brute-force inner-product kernel (`faiss.knn`, what `IndexFlatIP.search`
  runs) over the database's own float32 array when codes are stored float32 (no copy), else
  over a float32 mirror grown with the database. It asks for k + slack neighbours and
  widens until every vector within the float32 rounding margin of the k-th is in, so the
  votes equal numpy brute force (`filtering.vote`) bit for bit.
- ivf: `IndexIVFFlat` (or `IndexIVFScalarQuantizer` 8-bit, `ivf_codes: sq8`) with inner
  product. It is trained (k-means on `ivf_train_vectors` per
  list, sampled evenly from all places so far) when first built, and trained anew, with every
  vector re-added, each time the map has grown `ivf_retrain_growth` times since; between those
  milestones new places are appended to the trained lists. The coarse quantizer is an HNSW
  graph over the centroids, so choosing the lists costs little even with 16k of them.
- hnsw: `IndexHNSWFlat`, appended to vector by vector; no training, but slow to build.
- auto: exact up to `ann_threshold_places`, ivf beyond; exact at any size when exact search
  runs on a GPU.

Exact search runs in faiss on the CPU, or (`exact_backend: torch`, which `auto` picks where
torch sees a GPU) as torch matrix products on `torch_device` (`loopclosure.device_search`): a
GPU holds every stage-I vector and scans them all for a query. Both propose, and the same
exact re-scoring decides.

The index is not saved with a map: the first query after loading builds it (exact: one norm
pass over the codes; IVF: a training run, minutes at a million places, docs/benchmarks.md). A retrain at a growth
milestone stalls that one query for as long; doing it beside the stream is left to a caller
that needs it.

Excluded places: the exclusion window of a streaming session is a suffix of the database,
searched as the id range [0, first excluded) (`IDSelectorRange`, or a prefix of the array in
exact mode); any other set is removed by `IDSelectorNot(IDSelectorBatch)` (ivf, hnsw) or by
asking for more neighbours and dropping the excluded ones (exact).
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from loopclosure.config import FilteringConfig
from loopclosure.device_search import TorchExactSearch, resolve_backend
from loopclosure.filtering import max_row_norm, similarity_margin, widen_until_complete

Rows = Callable[[int, int], np.ndarray]  # (start, stop) vector ids -> float32 (stop - start, d)


@contextlib.contextmanager
def faiss_threads(n: int) -> Iterator[None]:
    """faiss's OpenMP threads for one call (on shared cores, spinning threads take them from each
    other and from other processes), and its brute force through BLAS from a few queries on (the
    wheel's default waits for thousands, which scans a keyframe's queries slower; the figures are
    in docs/benchmarks.md, "Thread settings")."""
    import faiss

    before = faiss.omp_get_max_threads(), faiss.cvar.distance_compute_blas_threshold
    faiss.omp_set_num_threads(n)
    faiss.cvar.distance_compute_blas_threshold = 1
    try:
        yield
    finally:
        faiss.omp_set_num_threads(before[0])
        faiss.cvar.distance_compute_blas_threshold = before[1]


def auto_nlist(n_vectors: int) -> int:
    """4 sqrt(N) lists, as a power of two in [64, 16384]."""
    return int(min(16384, max(64, 2 ** round(math.log2(max(1.0, 4.0 * math.sqrt(n_vectors)))))))


# The settings that shape a built index; the others (probes, search breadth, threads, blocks,
# candidates fetched) are read at each query, so changing them keeps the index (`retune`).
BUILD_SETTINGS = frozenset({
    "index", "exact_backend", "torch_device", "torch_storage", "ann_threshold_places", "ivf_nlist", "ivf_codes",
    "ivf_train_vectors", "ivf_retrain_growth", "hnsw_m", "hnsw_ef_construction",
})  # fmt: skip


def same_build(a: FilteringConfig, b: FilteringConfig) -> bool:
    """Whether an index built under `a` is the one `b` would build."""
    return all(getattr(a, name) == getattr(b, name) for name in BUILD_SETTINGS)


class StageOneIndex:
    """Nearest stage-I vectors of a database of `per_place` vectors per place."""

    def __init__(self, config: FilteringConfig, dim: int, per_place: int) -> None:
        self.config = config
        self.dim = dim
        self.per_place = per_place
        self.n_places = 0  # places the index holds
        self.max_norm = 0.0  # largest stage-I vector norm seen (the exactness margin needs it)
        self.kind = "exact" if config.index in ("auto", "exact") else config.index
        self._mirror: np.ndarray | None = None  # float32 vectors for exact search (compact storage)
        torch_exact = self.kind == "exact" and resolve_backend(config) == "torch"
        self._device = (
            TorchExactSearch(
                dim, config.torch_device, config.torch_block_rows, config.faiss_threads, config.torch_storage
            )  # fmt: skip
            if torch_exact
            else None
        )
        self._index: Any = None  # faiss index (ivf, hnsw); faiss's stubs cover little of its API
        self._trained_at = 0  # places when the IVF lists were trained
        self.build_seconds: list[tuple[str, int, float]] = []  # (what, places, seconds), newest last

    def retune(self, config: FilteringConfig) -> None:
        """Take `config`'s search-time settings (IVF probes, HNSW breadth, threads, torch blocks)
        without rebuilding: an IVF over 1M places takes minutes to train."""
        if not same_build(self.config, config):
            raise ValueError("retune: the index's build settings differ; build a new index")
        self.config = config
        if self._device is not None:
            self._device.block_rows, self._device.cpu_threads = config.torch_block_rows, config.faiss_threads

    @property
    def search_device(self) -> str | None:
        """The torch device exact search runs on ('cuda', 'cpu'), or None (faiss, or approximate)."""
        return None if self._device is None else self._device.device

    @property
    def search_storage(self) -> str | None:
        """The torch device copy's precision ('float16', 'float32'), or None (faiss, or approximate)."""
        return None if self._device is None else self._device.storage

    # ---- keeping up with the database ---------------------------------------------------
    def sync(self, n_places: int, rows: Rows, view: np.ndarray | None = None) -> None:
        """Take in places [self.n_places, n_places). `view`: the database's (N, d) float32
        vectors when it stores float32 (exact search reads them without a copy)."""
        if n_places < self.n_places:
            raise ValueError(f"the stage-I index holds {self.n_places} places, the database only {n_places}")
        if n_places == self.n_places:
            return
        start_vec, stop_vec = self.n_places * self.per_place, n_places * self.per_place
        on_gpu = self._device is not None and self._device.on_gpu
        if self.config.index == "auto" and self.kind == "exact" and n_places > self.config.ann_threshold_places:
            if not on_gpu:  # a GPU scans a city exactly in time; two CPU cores do not
                self.kind, self._mirror, self._device = "ivf", None, None
        exact = self.kind == "exact"
        if exact and self._device is not None and self.n_places == 0:  # a bulk load: one allocation
            self._device.reserve(stop_vec)
        elif exact and self._device is None and view is None:
            self._mirror = _grow(self._mirror, stop_vec, self.dim)
        for lo in range(start_vec, stop_vec, 1 << 18):  # each chunk read once (int8 storage dequantises)
            hi = min(stop_vec, lo + (1 << 18))
            part = rows(lo, hi)
            self.max_norm = max(self.max_norm, max_row_norm(part))
            if exact and self._device is not None:
                self._device.write(lo, part)
            elif exact and view is None:
                assert self._mirror is not None  # grown above
                self._mirror[lo:hi] = part
        if exact:
            self.n_places = n_places
            return
        t0 = time.perf_counter()
        with faiss_threads(max(1, self.config.faiss_threads)):
            if self.kind == "ivf":
                if self._index is None or n_places >= self.config.ivf_retrain_growth * self._trained_at:
                    self._build_ivf(n_places, rows)
                    what = "ivf train + add"
                else:
                    self._add(rows, start_vec, stop_vec)
                    what = "ivf add"
            else:
                if self._index is None:
                    import faiss

                    self._index = faiss.IndexHNSWFlat(self.dim, self.config.hnsw_m, faiss.METRIC_INNER_PRODUCT)
                    self._index.hnsw.efConstruction = self.config.hnsw_ef_construction
                self._add(rows, start_vec, stop_vec)
                what = "hnsw add"
        self.build_seconds.append((what, n_places - self.n_places, time.perf_counter() - t0))
        del self.build_seconds[:-16]
        self.n_places = n_places

    def _build_ivf(self, n_places: int, rows: Rows) -> None:
        import faiss

        n_vectors = n_places * self.per_place
        nlist = min(self.config.ivf_nlist or auto_nlist(n_vectors), n_vectors)
        index: Any
        quantizer = faiss.IndexHNSWFlat(self.dim, 32, faiss.METRIC_INNER_PRODUCT)
        if self.config.ivf_codes == "sq8":
            index = faiss.IndexIVFScalarQuantizer(
                quantizer, self.dim, nlist, faiss.ScalarQuantizer.QT_8bit, faiss.METRIC_INNER_PRODUCT
            )
        else:
            index = faiss.IndexIVFFlat(quantizer, self.dim, nlist, faiss.METRIC_INNER_PRODUCT)
        index.cp.niter = 10
        index.cp.spherical = True  # inner product: unit centroids, or the longest ones take every vector
        n_train = min(n_vectors, self.config.ivf_train_vectors * nlist)
        picks = np.unique(np.linspace(0, n_vectors - 1, n_train).astype(np.int64))
        sample = _gather(rows, picks)
        # k-means assigns with a flat search (BLAS, batched); the graph is built over the centroids after
        clustering = faiss.Clustering(self.dim, nlist, index.cp)
        flat = faiss.IndexFlatIP(self.dim)
        clustering.train(np.ascontiguousarray(sample, np.float32), flat)
        centroids = faiss.vector_to_array(clustering.centroids).reshape(nlist, self.dim)
        quantizer.hnsw.efConstruction = 40
        quantizer.add(centroids)
        if self.config.ivf_codes == "sq8":  # the per-dimension ranges of the 8-bit codes
            index.sq.train(np.ascontiguousarray(sample, np.float32))
        index.is_trained = True
        self._index, self._quantizer = index, quantizer
        self._trained_at = n_places
        self._add(rows, 0, n_vectors)

    def _add(self, rows: Rows, start: int, stop: int) -> None:
        for lo in range(start, stop, 1 << 18):
            part = np.ascontiguousarray(rows(lo, min(stop, lo + (1 << 18))), np.float32)
            self._index.add(part)

    # ---- search -------------------------------------------------------------------------
    def candidates(
        self, query: np.ndarray, k: int, excluded: np.ndarray, view: np.ndarray | None = None
    ) -> list[np.ndarray]:
        """Per query row, ascending vector ids proposed as its k nearest outside the `excluded`
        places (sorted, unique); exact mode: a superset of the exact top k."""
        query = np.ascontiguousarray(query, np.float32)
        n_places = self.n_places
        n_allowed_vectors = (n_places - len(excluded)) * self.per_place
        k = min(k, n_allowed_vectors)
        if k <= 0:
            return [np.empty(0, np.int64) for _ in query]
        # a suffix exclusion is the id range [0, limit)
        limit = int(excluded[0]) if len(excluded) and excluded[0] + len(excluded) == n_places else None
        with faiss_threads(max(1, self.config.faiss_threads)):
            if self.kind == "exact":
                return self._exact(query, k, n_allowed_vectors, excluded, limit, view)
            return self._approximate(query, k, excluded, limit)

    def _exact(
        self,
        query: np.ndarray,
        k: int,
        n_allowed: int,
        excluded: np.ndarray,
        limit: int | None,
        view: np.ndarray | None,
    ) -> list[np.ndarray]:
        if self._device is not None:
            stop = self.n_places * self.per_place if limit is None else limit * self.per_place
            excluded_ids = np.empty(0, np.int64) if limit is not None else excluded_ids_of(excluded, self.per_place)
            return self._device.propose(query, k, stop, excluded_ids, self.max_norm)
        import faiss

        mirror = view if view is not None else self._mirror
        assert mirror is not None  # kept for compact storage, else the database's own view is given
        base = mirror[: self.n_places * self.per_place]
        if limit is not None:
            base, excluded = base[: limit * self.per_place], excluded[:0]
        excluded_ids = excluded_ids_of(excluded, self.per_place)

        def fetch(todo: np.ndarray, kk: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
            # excluded ids are dropped after the search, so ask for as many more
            sims, ids = faiss.knn(query[todo], base, min(kk + len(excluded_ids), len(base)),
                                  metric=faiss.METRIC_INNER_PRODUCT)  # fmt: skip
            for s, i in zip(sims, ids):
                keep = (i >= 0) & ~np.isin(i, excluded_ids) if len(excluded_ids) else i >= 0
                yield s[keep][:kk], i[keep][:kk]

        return widen_until_complete(len(query), k, n_allowed, similarity_margin(query, self.max_norm), fetch)

    def _approximate(self, query: np.ndarray, k: int, excluded: np.ndarray, limit: int | None) -> list[np.ndarray]:
        import faiss

        selector: Any
        params: Any
        if limit is not None:
            selector = faiss.IDSelectorRange(0, limit * self.per_place)
            keep_alive: tuple = (selector,)
        elif len(excluded):
            batch = faiss.IDSelectorBatch(excluded_ids_of(excluded, self.per_place))
            selector = faiss.IDSelectorNot(batch)
            keep_alive = (batch, selector)
        else:
            selector, keep_alive = None, ()
        fetch = int(math.ceil(k * self.config.ann_candidates_factor))
        if self.kind == "ivf":
            params = _faiss_api().SearchParametersIVF(nprobe=min(self.config.ivf_nprobe, self._index.nlist))
            quantizer_params = _faiss_api().SearchParametersHNSW(efSearch=max(64, 2 * params.nprobe))
            params.quantizer_params = quantizer_params
        else:
            params = _faiss_api().SearchParametersHNSW(efSearch=max(self.config.hnsw_ef_search, fetch))
        if selector is not None:
            params.sel = selector
        _, ids = self._index.search(query, fetch, params=params)
        del keep_alive
        return [np.sort(i[i >= 0]) for i in ids]


def excluded_ids_of(places: np.ndarray, per_place: int) -> np.ndarray:
    """Vector ids of the given places."""
    return (np.asarray(places, np.int64)[:, None] * per_place + np.arange(per_place)).ravel()


def _grow(array: np.ndarray | None, rows: int, dim: int) -> np.ndarray:
    """A float32 (capacity, d) buffer holding at least `rows` rows, contents kept (doubling)."""
    if array is not None and len(array) >= rows:
        return array
    grown = np.empty((max(rows, 2 * (0 if array is None else len(array)), 1024), dim), np.float32)
    if array is not None:
        grown[: len(array)] = array
    return grown


def _gather(rows: Rows, picks: np.ndarray, chunk: int = 1 << 18) -> np.ndarray:
    """Rows at sorted vector ids `picks`, read chunk by chunk of the id range."""
    parts = []
    for lo in range(0, int(picks[-1]) + 1, chunk):
        sel = picks[(picks >= lo) & (picks < lo + chunk)]
        if len(sel):
            parts.append(rows(lo, min(int(picks[-1]) + 1, lo + chunk))[sel - lo])
    return np.concatenate(parts)


def _faiss_api() -> Any:
    """faiss, untyped: its stubs lack the search-parameter classes this module uses."""
    import faiss

    return faiss
