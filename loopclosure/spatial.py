"""Stage II, spatial matching: how consistently a candidate's grid maps onto the query's.

For every candidate cell (i, j) its best query cell (k, l) is the anchor; the cells on the
anchor's row and column whose own best match keeps the same offset (k - i, l - j) count
towards the score. Written as counts: with D[i, j] the displacement of cell (i, j), the row
part of an anchor is the size of its displacement group within row i, so a row contributes
the sum of its squared group sizes (columns likewise). That closed form is vectorised over
all candidates; `spatial_score_literal` is the paper's loop, kept as the reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SpatialResult:
    scores: np.ndarray  # (C,) in [0, 1]; 1 = every cell shares one displacement
    raw: np.ndarray  # (C,) the paper's integer counts
    shifts: np.ndarray  # (C, 2) dominant (row, column) displacement in grid cells


# Elements per torch copy: at or below ATen's parallel grain (32,768), a copy runs in the calling
# thread and never wakes torch's OpenMP pool, whose spinning threads would take the cores from
# the BLAS product that follows (and, in a SLAM run, from the backbone).
_SERIAL_COPY = 16384


def as_float32(a: np.ndarray) -> np.ndarray:
    """float32 values of stored grids. numpy widens float16 one value at a time (1.4 ms for 50
    candidates' grids on a Zen 4); torch's vectorised kernel, run serially in pieces, takes 0.25.
    torch is imported here, on first use: the backbone has loaded it in any detector."""
    if a.dtype != np.float16:
        return a.astype(np.float32, copy=False)
    import torch

    # torch wants a writable buffer (a memory-mapped map's slice is read-only): copy only then.
    src = torch.from_numpy(np.require(a, requirements=["C", "W"]).reshape(-1))
    out = torch.empty(src.shape, dtype=torch.float32)
    for start in range(0, src.numel(), _SERIAL_COPY):
        out[start : start + _SERIAL_COPY].copy_(src[start : start + _SERIAL_COPY])
    return out.numpy().reshape(a.shape)


def best_query_cells(query: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """query (gh, gw, d), candidates (C, gh, gw, d) -> (C, gh, gw) flat index of the best query cell."""
    gh, gw, d = query.shape
    q = as_float32(query.reshape(gh * gw, d))
    c = as_float32(candidates.reshape(-1, d))
    # nearest in L2: argmin |c - q|^2 = argmax 2 c.q - |q|^2 (cosine when codes are unit length)
    affinity = c @ (2.0 * q.T)
    affinity -= np.einsum("nd,nd->n", q, q)[None, :]
    return np.argmax(affinity, axis=1).reshape(candidates.shape[0], gh, gw)


def consistency_counts(best: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C, gh, gw) best-cell indices -> raw scores (C,) and dominant shifts (C, 2)."""
    n, gh, gw = best.shape
    rows, cols = np.divmod(best, gw)
    d_row = rows - np.arange(gh)[None, :, None] + (gh - 1)
    d_col = cols - np.arange(gw)[None, None, :] + (gw - 1)
    n_codes = (2 * gh - 1) * (2 * gw - 1)
    code = d_row * (2 * gw - 1) + d_col  # (C, gh, gw) in [0, n_codes)

    row_key = (np.arange(n)[:, None, None] * gh + np.arange(gh)[None, :, None]) * n_codes + code
    row_counts = np.bincount(row_key.ravel(), minlength=n * gh * n_codes).reshape(n, -1)
    col_key = (np.arange(n)[:, None, None] * gw + np.arange(gw)[None, None, :]) * n_codes + code
    col_counts = np.bincount(col_key.ravel(), minlength=n * gw * n_codes).reshape(n, -1)
    raw = (row_counts.astype(np.int64) ** 2).sum(1) + (col_counts.astype(np.int64) ** 2).sum(1)

    totals = np.bincount((np.arange(n)[:, None, None] * n_codes + code).ravel(), minlength=n * n_codes)
    dominant = totals.reshape(n, n_codes).argmax(1)
    shifts = np.stack(np.divmod(dominant, 2 * gw - 1), axis=1) - np.array([gh - 1, gw - 1])
    return raw, shifts


def max_raw_score(gh: int, gw: int) -> int:
    """All cells sharing one displacement: each row gives gw^2, each column gh^2."""
    return gh * gw * gw + gw * gh * gh


def check_grids(query: np.ndarray, candidates: np.ndarray, grid: tuple[int, ...] | None = None) -> None:
    """(n, gh, gw, d) candidate grids of the query's shape (and of `grid`, when a batch shares one)."""
    if candidates.ndim != 4 or candidates.shape[1:] != query.shape or (grid is not None and query.shape != grid):
        raise ValueError(f"candidate grids {candidates.shape} do not match the query grid {query.shape}")


def spatial_scores(query: np.ndarray, candidates: np.ndarray, chunk: int = 64) -> SpatialResult:
    """Score all candidates against one query, `chunk` candidates per matrix product."""
    check_grids(query, candidates)
    gh, gw, _ = query.shape
    raws, shifts = [], []
    for start in range(0, candidates.shape[0], chunk):
        raw, shift = consistency_counts(best_query_cells(query, candidates[start : start + chunk]))
        raws.append(raw)
        shifts.append(shift)
    if not raws:
        return SpatialResult(np.empty(0, np.float32), np.empty(0, np.int64), np.empty((0, 2), np.int64))
    raw = np.concatenate(raws)
    return SpatialResult((raw / max_raw_score(gh, gw)).astype(np.float32), raw, np.concatenate(shifts))


def spatial_score_literal(query: np.ndarray, candidate: np.ndarray) -> int:
    """The paper's Algorithm 2 for one candidate, loop for loop (reference for tests)."""
    gh, gw, _ = query.shape
    best = {}
    for i in range(gh):
        for j in range(gw):
            dists = [[float(np.sum((candidate[i, j] - query[k, m]) ** 2)) for m in range(gw)] for k in range(gh)]
            flat = int(np.argmin(np.asarray(dists)))
            best[i, j] = divmod(flat, gw)
    score = 0
    for i in range(gh):
        for j in range(gw):
            k, m = best[i, j]
            offset = (k - i, m - j)
            for jj in range(gw):  # along the anchor's row
                kk, ll = best[i, jj]
                if (kk - i, ll - jj) == offset:
                    score += 1
            for ii in range(gh):  # along the anchor's column
                kk, ll = best[ii, j]
                if (kk - ii, ll - j) == offset:
                    score += 1
    return score
