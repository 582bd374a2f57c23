"""Stage I, the filtering stage: histogram voting over nearest stage-I vectors.

Each of a query's stage-I vectors finds its k nearest database vectors; every neighbour is
one vote for the place it belongs to; the places with the most votes go on to spatial
matching. Excluded places (the recent past, in SLAM) are removed before the neighbours are
chosen, so they can never crowd true candidates out of the top N.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Candidates:
    """Places ranked by votes (ties broken by summed similarity of their votes)."""

    places: np.ndarray  # (C,) database place indices, best first
    votes: np.ndarray  # (C,) raw vote counts
    scores: np.ndarray  # (C,) votes normalised to [0, 1]

    def __len__(self) -> int:
        return int(self.places.shape[0])


def vote(
    query: np.ndarray,
    database: np.ndarray,
    k_neighbours: int,
    num_candidates: int,
    excluded: np.ndarray | None = None,
) -> Candidates:
    """query (n, d); database (P, n, d) stage-I codes; excluded: place indices never to return."""
    n_places, per_place, dim = database.shape
    if query.ndim != 2 or query.shape[1] != dim:
        raise ValueError(f"stage-I query must be (n, {dim}), got {query.shape}")
    allowed = np.ones(n_places, dtype=bool)
    if excluded is not None and len(excluded):
        excluded = np.asarray(excluded, dtype=np.int64)
        if excluded.min() < 0 or excluded.max() >= n_places:
            raise ValueError(f"excluded place indices must lie in [0, {n_places}), got {excluded.min()}..{excluded.max()}")
        allowed[excluded] = False
    n_allowed = int(allowed.sum())
    if n_allowed == 0:
        return Candidates(np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.float32))

    sims = query.astype(np.float32, copy=False) @ database.reshape(-1, dim).T.astype(np.float32, copy=False)
    if n_allowed < n_places:
        sims.reshape(len(query), n_places, per_place)[:, ~allowed, :] = -np.inf
    k = min(k_neighbours, n_allowed * per_place)
    n_vectors = sims.shape[1]
    if k < n_vectors:
        # per row: the k-th largest value as a threshold, then the first k at or above it;
        # avoids argpartition's full negated copy and index array (half the query time at 100k)
        neighbours = np.empty((len(query), k), dtype=np.int64)
        for row, values in enumerate(sims):
            threshold = np.partition(values, n_vectors - k)[n_vectors - k]
            neighbours[row] = np.flatnonzero(values >= threshold)[:k]
    else:
        neighbours = np.broadcast_to(np.arange(n_vectors), sims.shape)
    neighbour_sims = np.take_along_axis(sims, neighbours, axis=1).ravel()
    neighbour_places = (neighbours // per_place).ravel()
    votes = np.bincount(neighbour_places, minlength=n_places)
    similarity = np.bincount(neighbour_places, weights=neighbour_sims, minlength=n_places)

    voted = np.flatnonzero(votes)
    order = np.lexsort((-similarity[voted], -votes[voted]))[:num_candidates]
    places = voted[order]
    max_votes = len(query) * min(k, per_place)
    return Candidates(places, votes[places], (votes[places] / max_votes).astype(np.float32))
