"""Stage I, the filtering stage: histogram voting over nearest stage-I vectors.

Each of a query's stage-I vectors finds its k nearest database vectors; every neighbour is
one vote for the place it belongs to; the places with the most votes go on to spatial
matching. Excluded places (the recent past, in SLAM) are removed before the neighbours are
chosen, so they can never crowd true candidates out of the top N.

The neighbours are decided on exact similarities: float64 sums of the (exact) products of
the float32 values, computed row by row in a fixed order. A float32 matrix product (BLAS,
faiss) only proposes candidates: every vector within twice its rounding bound of the k-th
similarity is re-scored exactly. So numpy brute force (`vote`) and an index
(`loopclosure.ann_index`) that proposes a superset of the same vectors choose the same
neighbours, votes and tie order, bit for bit, whatever order their kernels sum in.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

# unit roundoff of float32: a d-term float32 dot product is within d*u*|q||x| of the exact value
F32_UNIT_ROUNDOFF = float(np.finfo(np.float32).eps) / 2.0


@dataclass(frozen=True)
class Candidates:
    """Places ranked by votes (ties broken by summed similarity of their votes)."""

    places: np.ndarray  # (C,) database place indices, best first
    votes: np.ndarray  # (C,) raw vote counts
    scores: np.ndarray  # (C,) votes normalised to [0, 1]

    def __len__(self) -> int:
        return int(self.places.shape[0])


def empty_candidates() -> Candidates:
    return Candidates(np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.float32))


def similarity_margin(query: np.ndarray, max_norm: float) -> np.ndarray:
    """(n,) how far under the k-th float32 similarity an exact top-k vector can lie: twice the
    rounding bound of a float32 dot product, gamma_d |q| max|x|, doubled again for safety."""
    d = query.shape[1]
    gamma = d * F32_UNIT_ROUNDOFF / (1.0 - d * F32_UNIT_ROUNDOFF)
    norms = np.linalg.norm(query.astype(np.float64), axis=1)
    return 4.0 * gamma * norms * max(float(max_norm), 1e-30) + 1e-300


Fetch = Callable[[np.ndarray, int], Iterable[tuple[np.ndarray, np.ndarray]]]


def widen_until_complete(
    n_rows: int, k: int, n_allowed: int, margin: np.ndarray, fetch: Fetch, first: int | None = None
) -> list[np.ndarray]:
    """Per query row, ascending ids of every vector within `margin[row]` of the k-th largest
    float32 similarity: a superset of the exact top k, for `rank_neighbours` to decide.

    `fetch(rows, kk)` gives, for each of those rows, its best (at most) kk allowed similarities,
    descending, and their ids. A row is settled once the last fetched value lies below the
    margin of the k-th, so nothing unfetched can be within it; the others ask for twice as
    many. An index's exact mode only supplies `fetch`; `first` (default k + max(8, k/4)) is
    how many the first fetch asks for, more where a fetch costs the same for any kk (a GPU)."""
    out: list[np.ndarray | None] = [None] * n_rows
    todo = np.arange(n_rows)
    kk = min(max(k, first or k + max(8, k // 4)), n_allowed)
    while len(todo):
        again = []
        for row, (s, i) in zip(todo, fetch(todo, kk)):
            floor = s[k - 1] - margin[row]
            if len(i) < kk or kk >= n_allowed or s[-1] < floor:
                out[row] = np.sort(i[s >= floor])
            else:
                again.append(row)
        todo, kk = np.asarray(again, np.int64), min(2 * kk, n_allowed)
    return out  # type: ignore[return-value]


def max_row_norm(rows: np.ndarray, chunk: int = 1 << 16) -> float:
    """Largest L2 norm among (m, d) rows, a little rounded up (the margin needs an upper bound)."""
    best = 0.0
    for start in range(0, len(rows), chunk):
        part = np.asarray(rows[start : start + chunk], dtype=np.float64)
        if len(part):
            best = max(best, float(np.sqrt(np.einsum("ij,ij->i", part, part).max())))
    return best * (1.0 + 1e-6)


def exact_similarities(query_row: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(m,) float64 inner products of one query vector with (m, d) rows.

    Products of float32 values are exact in float64 and each row is summed on its own, in the
    same order whatever the other rows: the value of a vector does not depend on which set it
    was scored in (a BLAS product's does, in the last bit)."""
    return (np.asarray(rows, dtype=np.float64) * np.asarray(query_row, dtype=np.float64)).sum(axis=1)


def rank_neighbours(
    query: np.ndarray,
    rows: Callable[[np.ndarray], np.ndarray],
    candidates: list[np.ndarray],
    k: int,
    per_place: int,
    num_candidates: int,
) -> Candidates:
    """Votes from each query row's k exact nearest among its candidate vector ids.

    `candidates[r]`: ascending vector ids, a superset of row r's exact top k (or an index's
    approximation of it); `rows(ids)` gives those vectors. Ties at the k-th similarity go to
    the lower id; places tied on votes are ordered by summed similarity, then by index."""
    ids_parts, sims_parts = [], []
    for row, cand in enumerate(candidates):
        if not len(cand):
            continue
        exact = exact_similarities(query[row], rows(cand))
        if len(cand) > k:
            threshold = np.partition(exact, len(cand) - k)[len(cand) - k]
            keep = np.flatnonzero(exact >= threshold)[:k]
            cand, exact = cand[keep], exact[keep]
        ids_parts.append(cand)
        sims_parts.append(exact)
    if not ids_parts:
        return empty_candidates()
    neighbour_places = np.concatenate(ids_parts) // per_place
    places, inverse = np.unique(neighbour_places, return_inverse=True)
    votes = np.bincount(inverse)
    similarity = np.bincount(inverse, weights=np.concatenate(sims_parts))
    order = np.lexsort((-similarity, -votes))[:num_candidates]
    max_votes = len(query) * min(k, per_place)
    return Candidates(places[order], votes[order], (votes[order] / max_votes).astype(np.float32))


def allowed_mask(n_places: int, excluded: np.ndarray | None) -> np.ndarray:
    """Places that may be returned; `excluded` indices must lie in [0, n_places)."""
    allowed = np.ones(n_places, dtype=bool)
    if excluded is not None and len(excluded):
        excluded = np.asarray(excluded, dtype=np.int64)
        if excluded.min() < 0 or excluded.max() >= n_places:
            raise ValueError(
                f"excluded place indices must lie in [0, {n_places}), got {excluded.min()}..{excluded.max()}"
            )
        allowed[excluded] = False
    return allowed


def vote(
    query: np.ndarray,
    database: np.ndarray,
    k_neighbours: int,
    num_candidates: int,
    excluded: np.ndarray | None = None,
    max_norm: float | None = None,
) -> Candidates:
    """Brute force: query (n, d); database (P, n, d) stage-I codes; excluded: place indices never
    to return. `max_norm` bounds the database vectors' norms (computed when not given)."""
    n_places, per_place, dim = database.shape
    if query.ndim != 2 or query.shape[1] != dim:
        raise ValueError(f"stage-I query must be (n, {dim}), got {query.shape}")
    allowed = allowed_mask(n_places, excluded)
    n_allowed = int(allowed.sum())
    if n_allowed == 0:
        return empty_candidates()

    flat = database.reshape(-1, dim)
    sims = query.astype(np.float32, copy=False) @ flat.T.astype(np.float32, copy=False)
    if n_allowed < n_places:
        sims.reshape(len(query), n_places, per_place)[:, ~allowed, :] = -np.inf
    k = min(k_neighbours, n_allowed * per_place)
    n_vectors = sims.shape[1]
    if k < n_vectors:
        # per row: the k-th largest float32 value as a threshold (np.partition avoids argpartition's
        # negated copy and index array), then every vector that may be in the exact top k
        margin = similarity_margin(query, max_row_norm(flat) if max_norm is None else max_norm)
        candidates = []
        for row, values in enumerate(sims):
            threshold = np.partition(values, n_vectors - k)[n_vectors - k]
            candidates.append(np.flatnonzero(values >= threshold - margin[row]))
    else:
        candidates = [np.arange(n_vectors)] * len(query)
    return rank_neighbours(query, lambda ids: flat[ids], candidates, k, per_place, num_candidates)
