"""Sequence matching on SSM-VPR stage-II scores (SeqSLAM's idea; the paper's future work).

Why: one frame can look like many places, but a run of L consecutive query frames matching a
run of L consecutive places rarely happens by accident. The score of query q -> place r
aggregates stage-II scores along a line of the query x place score matrix::

    forward revisit:  s(q-k, r - o_k)        reverse revisit:  s(q-k, r + o_k),   k = 0..L-1

with o_k = floor(v * k + 1/2) for each configured speed v (SeqSLAM's slopes: places advanced
per query step). The best (direction, speed) wins. L = 1 is single-frame recognition.

Missing terms. A term does not exist before the first query (start-up), outside the database
(its edges), or for a place the earlier query could not have matched (not yet in the database,
or inside that query's exclusion window: ``limit``). By default (``missing: zero``) such a term
counts as score 0, i.e. no evidence. Averaging over the terms that exist instead ("skip") makes
a short sequence as noisy as one frame while it competes with full-length averages, whose
spread is smaller, so at the start of a traverse or at a database edge a lucky alias outranks
real sequences. With zero fill a sequence never scores more than full evidence could give it, but
a line of n < L terms scores n / L of what the same match scores at full length: the first
keyframes after a seam, and the revisit of a stream's first places (whose line runs off the
database's start), lose most of their evidence. ``missing: shrink`` (the detector's default)
takes the mean of the n terms that exist times sqrt(n / L): a wrong line's spread is then that
of a full line (n terms of spread s average to s / sqrt(n), which the factor brings to
s / sqrt(L)), so short lines compete fairly with full ones, and a right match of n terms counts
sqrt(n / L) of its full-length lead instead of n / L (docs/loop_decisions.md).

Two implementations of the same definition:
- :func:`sequence_score_matrix` / :func:`match_sequences`: batch, over a dense score matrix.
- :class:`SequenceMatcher`: streaming. It keeps the last L-1 queries (their stage-II grids, or
  any token the scorer understands) and scores only the terms its candidates need, once each
  (a per-query cache): about L x N spatial scores per query. Its result equals the batch result.

Candidates of query q: the stage-II candidates (stage I's top N, optionally only the best K by
stage-II score) plus the places that continue the previous query's best sequences, so a
sequence once found is followed even where stage I misses the next place.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from loopclosure.config import SequenceMatchConfig
from loopclosure.errors import LoopClosureInputError
from loopclosure.saved_state import saved_finite, saved_ints

Direction = Literal["forward", "reverse"]
Scorer = Callable[[Any, np.ndarray], np.ndarray]
"""(token of an earlier query, place indices) -> stage-II scores of that query against them."""
BatchScorer = Callable[[list[tuple[Any, np.ndarray]]], list[np.ndarray]]
"""[(token, place indices), ...] -> the scorer's scores of each, in one call (see `SequenceMatcher`)."""
Segments = Callable[[np.ndarray], np.ndarray]
"""place indices -> the id of the stretch of places each lies on (see `SequenceMatcher`)."""

_SIGN: dict[str, int] = {"forward": -1, "reverse": +1}


def directions(config: SequenceMatchConfig) -> tuple[Direction, ...]:
    return ("forward", "reverse") if config.direction == "both" else (config.direction,)  # type: ignore[return-value]


def offsets(config: SequenceMatchConfig, speed: float) -> np.ndarray:
    """Places travelled after k query steps at `speed`, k = 0..L-1 (round half up)."""
    return np.floor(speed * np.arange(config.length) + 0.5).astype(np.int64)


def continuation_steps(config: SequenceMatchConfig) -> np.ndarray:
    """How far (in places) one query step moves a sequence, over the configured speeds."""
    return np.unique(np.floor(np.asarray(config.speeds) + 0.5).astype(np.int64))


def aggregate(terms: np.ndarray, config: SequenceMatchConfig) -> np.ndarray:
    """(L, ...) terms, NaN where missing -> (...) sequence scores (float64).

    Shared by both implementations so they round alike; the sum runs k = 0..L-1 in order."""
    missing = np.isnan(terms)
    if config.missing == "zero":
        filled = np.where(missing, 0.0, terms)
        if config.aggregation == "median":
            return np.median(filled, axis=0)
        total = np.zeros(terms.shape[1:], np.float64)
        for k in range(terms.shape[0]):
            total += filled[k]
        return total / terms.shape[0]
    present = np.maximum((~missing).sum(axis=0), 1)
    if config.aggregation == "median":
        with np.errstate(all="ignore"):
            out = np.nanmedian(np.where(np.all(missing, axis=0), 0.0, terms), axis=0)
    else:
        out = np.zeros(terms.shape[1:], np.float64)
        for k in range(terms.shape[0]):
            out += np.where(missing[k], 0.0, terms[k])
        out /= present
    if config.missing == "shrink":  # n terms weigh as sqrt(n / L) of a full line's evidence
        out *= np.sqrt(present / terms.shape[0])
    return out


@dataclass(frozen=True)
class SequenceMatch:
    """One query's outcome: its best sequence and every candidate's sequence score."""

    place: int | None  # best place, None when there was no candidate
    score: float  # its sequence score (the single-frame score when L = 1)
    direction: Direction | None
    speed: float
    single_score: float  # s(q, place): the stage-II score of the query alone
    terms: int  # how many of the L terms of the winning line exist
    candidates: np.ndarray  # (C,) places evaluated, ascending
    candidate_scores: np.ndarray  # (C,) their best sequence scores
    ranked: dict[str, np.ndarray] = field(default_factory=dict)  # direction -> best places, for continuation


def _top_k(places: np.ndarray, scores: np.ndarray, k: int | None) -> np.ndarray:
    """The k best places by score (stable: ties keep the given order); all when k is None."""
    if k is None or len(places) <= k:
        return places
    return places[np.argsort(-scores, kind="stable")[:k]]


def _continued(config: SequenceMatchConfig, previous: dict[str, np.ndarray] | None, limit: int) -> np.ndarray:
    """Places that continue the previous query's best sequences by one query step."""
    if config.length < 2 or not previous:
        return np.empty(0, np.int64)
    steps = continuation_steps(config)
    parts = [p[:, None] - _SIGN[d] * steps[None, :] for d, p in previous.items() if len(p)]
    if not parts:
        return np.empty(0, np.int64)
    out = np.unique(np.concatenate([p.ravel() for p in parts]))
    return out[(out >= 0) & (out < limit)]


def _decide(
    config: SequenceMatchConfig,
    cand: np.ndarray,
    by_line: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]],
    single: np.ndarray,
) -> SequenceMatch:
    """Pick the best (place, direction, speed) from per-line scores; first maximum wins.

    by_line[(direction, speed index)] = (scores (C,), existing terms (C,)) in candidate order."""
    if not len(cand):
        empty = np.empty(0)
        return SequenceMatch(
            None, 0.0, None, 1.0, 0.0, 0, cand, empty, {d: np.empty(0, np.int64) for d in directions(config)}
        )
    best = np.full(len(cand), -np.inf)
    best_line = np.zeros(len(cand), np.int64)
    lines = list(by_line)
    per_direction: dict[str, np.ndarray] = {}
    for i, line in enumerate(lines):
        scores = by_line[line][0]
        better = scores > best
        best = np.where(better, scores, best)
        best_line = np.where(better, i, best_line)
        d = line[0]
        per_direction[d] = scores if d not in per_direction else np.maximum(per_direction[d], scores)
    winner = int(np.argmax(best))
    direction, speed_index = lines[int(best_line[winner])]
    ranked = {d: cand[np.argsort(-s, kind="stable")[: config.continuations]] for d, s in per_direction.items()}
    return SequenceMatch(
        place=int(cand[winner]),
        score=float(best[winner]),
        direction=direction,  # type: ignore[arg-type]
        speed=float(config.speeds[speed_index]),
        single_score=float(single[winner]),
        terms=int(by_line[(direction, speed_index)][1][winner]),
        candidates=cand,
        candidate_scores=best,
        ranked=ranked,
    )


# ---------------------------------------------------------------------------------------- batch


def sequence_score_matrix(
    scores: np.ndarray,
    config: SequenceMatchConfig,
    limits: np.ndarray | None = None,
    place_segments: np.ndarray | None = None,
    query_segments: np.ndarray | None = None,
) -> dict[tuple[str, int], tuple[np.ndarray, np.ndarray]]:
    """Every (query, place) sequence score of a dense (Q, R) stage-II score matrix.

    limits[q]: query q may match places [0, limits[q]) only (default R). place_segments (R,) /
    query_segments (Q,): stretch ids; a line never crosses from one stretch to another (the
    term is missing). Returns, per line (direction, speed index), the (Q, R) scores and the
    (Q, R) count of existing terms; a pair whose own term is missing (r >= limits[q]) scores -inf."""
    s = np.asarray(scores, dtype=np.float64)
    n_query, n_places = s.shape
    limits = np.full(n_query, n_places, np.int64) if limits is None else np.asarray(limits, np.int64)
    p_seg = np.zeros(n_places, np.int64) if place_segments is None else np.asarray(place_segments, np.int64)
    q_seg = np.zeros(n_query, np.int64) if query_segments is None else np.asarray(query_segments, np.int64)
    valid = np.arange(n_places)[None, :] < limits[:, None]
    out: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}
    for direction in directions(config):
        for si, speed in enumerate(config.speeds):
            terms = np.full((config.length, n_query, n_places), np.nan)
            for k, o in enumerate(offsets(config, speed)):
                x = np.arange(n_places) + _SIGN[direction] * o
                ok_x = (x >= 0) & (x < n_places)
                earlier = np.arange(n_query) - k
                ok_q = earlier >= 0
                block = np.full((n_query, n_places), np.nan)
                rows = earlier[ok_q]
                sub = s[np.ix_(rows, x[ok_x])]
                sub[~valid[np.ix_(rows, x[ok_x])]] = np.nan  # the earlier query could not match that place
                sub[:, p_seg[x[ok_x]] != p_seg[np.flatnonzero(ok_x)]] = np.nan  # the line left the place's stretch
                sub[q_seg[rows] != q_seg[np.flatnonzero(ok_q)]] = np.nan  # the query's stretch began after it
                block[np.ix_(np.flatnonzero(ok_q), np.flatnonzero(ok_x))] = sub
                terms[k] = block
            agg = aggregate(terms, config)
            agg[~valid] = -np.inf
            out[(direction, si)] = (agg, (~np.isnan(terms)).sum(axis=0))
    return out


def match_sequences(
    scores: np.ndarray,
    config: SequenceMatchConfig,
    candidates: Sequence[np.ndarray] | None = None,
    limits: np.ndarray | None = None,
    centres: np.ndarray | None = None,
    place_segments: np.ndarray | None = None,
    query_segments: np.ndarray | None = None,
) -> list[SequenceMatch]:
    """Batch sequence matching over a dense (Q, R) score matrix.

    candidates[q]: the stage-II candidates of query q (default: every place it may match);
    the same selection as the streaming matcher (best K, then the continued sequences).
    centres[q]: subtracted from query q's scores before they are aggregated (the streaming
    matcher's `centre`). place_segments / query_segments: see `sequence_score_matrix`."""
    s = np.asarray(scores)
    if s.ndim != 2:
        raise LoopClosureInputError(f"scores must be a (queries, places) matrix, got shape {s.shape}")
    n_query, n_places = s.shape
    if centres is not None:
        s = s.astype(np.float64) - np.asarray(centres, np.float64).reshape(n_query, 1)
    limits = np.full(n_query, n_places, np.int64) if limits is None else np.asarray(limits, np.int64)
    if limits.shape != (n_query,) or (limits < 0).any() or (limits > n_places).any():
        raise LoopClosureInputError(
            f"limits must be {n_query} place counts in 0..{n_places} (one per query), got {limits.tolist()}"
        )
    lines = sequence_score_matrix(s, config, limits, place_segments, query_segments)
    out: list[SequenceMatch] = []
    previous: dict[str, np.ndarray] | None = None
    for q in range(n_query):
        if query_segments is not None and q and query_segments[q] != query_segments[q - 1]:
            previous = None  # a new stretch of queries continues nothing (the streaming matcher's reset)
        given = np.arange(limits[q]) if candidates is None else np.asarray(candidates[q], np.int64)
        given = given[(given >= 0) & (given < limits[q])]
        chosen = _top_k(given, s[q, given], config.sequence_candidates)
        cand = np.unique(np.concatenate([chosen, _continued(config, previous, int(limits[q]))]))
        by_line = {line: (agg[q, cand], n[q, cand]) for line, (agg, n) in lines.items()}
        match = _decide(config, cand, by_line, s[q, cand].astype(np.float64))
        out.append(match)
        previous = match.ranked
    return out


# ------------------------------------------------------------------------------------ streaming


@dataclass
class _Query:
    token: Any
    limit: int
    cache: dict[int, float]  # place -> score minus centre
    centre: float = 0.0


class SequenceMatcher:
    """Streaming sequence matching: one query in, its best sequence out.

    Call :meth:`continuations` before scoring a query's candidates (so the continued places are
    scored with them), then :meth:`step` with those scores. The earlier queries' terms are scored
    on demand through `scorer`, each (query, place) pair at most once.

    segments (optional): the stretch id of each place. The database of a stream is not always one
    continuous path: a prior map's places end where the session's begin, and two traverses
    streamed one after the other (`loop-eval`) meet where the first ends. A line never runs
    across such a seam: its terms beyond it are missing, as beyond the database's ends.

    batch_scorer (optional): the same scores for several earlier queries in one call. A step
    needs terms of up to L-1 earlier queries; on a GPU one call for all of them waits for the
    device once instead of L-1 times. It must return what `scorer` would, query by query."""

    def __init__(
        self,
        config: SequenceMatchConfig,
        scorer: Scorer,
        segments: Segments | None = None,
        batch_scorer: BatchScorer | None = None,
    ) -> None:
        self.config = config
        self.scorer = scorer
        self.batch_scorer = batch_scorer
        self.segments = segments
        self._recent: deque[_Query] = deque(maxlen=config.length)
        self._previous: dict[str, np.ndarray] | None = None
        self.scored_last_step = 0  # spatial scores computed by the last step (past and current query)

    def continuations(self, limit: int) -> np.ndarray:
        """Places the next query should score besides its stage-I candidates."""
        return _continued(self.config, self._previous, limit)

    def step(
        self,
        token: Any,
        places: np.ndarray,
        scores: np.ndarray,
        limit: int,
        extra_places: np.ndarray | None = None,
        extra_scores: np.ndarray | None = None,
        centre: float = 0.0,
    ) -> SequenceMatch:
        """Match the next query, given its stage-II `scores` against its candidate `places`.

        limit: the query may match places [0, limit) only (the database size minus the
        exclusion window); later queries' terms respect it too. extra_places/extra_scores:
        other places already scored against this query (the continuations, scored together
        with the candidates); they only spare scorer calls and do not change the result.
        centre: subtracted from every score of this query, now and as a later query's term
        (the detector passes the query's typical candidate score: sequences then add up how
        far each keyframe's match stands above its own field, whatever the world's level)."""
        places = np.asarray(places, np.int64).reshape(-1)
        scores = np.asarray(scores, np.float32).reshape(-1)
        if places.shape != scores.shape:
            raise ValueError(f"{len(places)} places but {len(scores)} scores")
        if not math.isfinite(centre):
            raise ValueError(f"centre must be finite, got {centre}")
        cache = {} if extra_places is None else dict(zip(np.asarray(extra_places, np.int64).tolist(),
                                                          np.asarray(extra_scores, np.float32).tolist()))  # fmt: skip
        cache.update(zip(places.tolist(), scores.tolist()))
        cache = {p: float(v) - centre for p, v in cache.items()}
        current = _Query(token, int(limit), cache, float(centre))
        self._recent.append(current)
        self.scored_last_step = 0

        keep = (places >= 0) & (places < limit)
        chosen = _top_k(places[keep], scores[keep], self.config.sequence_candidates)
        cand = np.unique(np.concatenate([chosen, self.continuations(int(limit))]))
        self._fill_many([(current, cand)])
        single = np.array([current.cache[int(p)] for p in cand], np.float64)

        history = list(reversed(self._recent))  # history[k] is query q-k
        lines_terms: dict[tuple[str, int], np.ndarray] = {}
        needed: dict[int, set[int]] = {}
        for direction in directions(self.config):
            for si, speed in enumerate(self.config.speeds):
                xs = cand[None, :] + _SIGN[direction] * offsets(self.config, speed)[:, None]  # (L, C)
                lines_terms[(direction, si)] = xs
                for k in range(1, min(self.config.length, len(history))):
                    row = xs[k]
                    needed.setdefault(k, set()).update(row[self._exists(row, cand, history[k].limit)].tolist())
        self._fill_many([(history[k], np.fromiter(sorted(xs), np.int64, len(xs))) for k, xs in needed.items()])

        by_line = {}
        for line, xs in lines_terms.items():
            terms = np.full(xs.shape, np.nan)
            for k in range(self.config.length):
                if k >= len(history):
                    break
                record = history[k]
                row = xs[k]
                ok = self._exists(row, cand, record.limit)
                terms[k, ok] = [record.cache[int(x)] for x in row[ok]]
            by_line[line] = (aggregate(terms, self.config), (~np.isnan(terms)).sum(axis=0))
        match = _decide(self.config, cand, by_line, single)
        self._previous = match.ranked
        return match

    def _exists(self, row: np.ndarray, cand: np.ndarray, limit: int) -> np.ndarray:
        """Which terms of a line exist: inside the places the earlier query could match, and on
        the same stretch of places as the candidate the line ends at."""
        ok = (row >= 0) & (row < limit)
        if self.segments is not None and ok.any():
            ok[ok] = np.asarray(self.segments(row[ok])) == np.asarray(self.segments(cand[ok]))
        return ok

    def _fill_many(self, wanted: list[tuple[_Query, np.ndarray]]) -> None:
        """Score the places each query has no score for yet: one scorer call a query, or one
        `batch_scorer` call for all where there is one."""
        todo = []
        for record, places in wanted:
            missing = np.array([p for p in places.tolist() if p not in record.cache], np.int64)
            if len(missing):
                todo.append((record, missing))
        if not todo:
            return
        if self.batch_scorer is not None and len(todo) > 1:
            scored = self.batch_scorer([(record.token, missing) for record, missing in todo])
        else:
            scored = [self.scorer(record.token, missing) for record, missing in todo]
        for (record, missing), values in zip(todo, scored, strict=True):
            values = np.asarray(values, np.float32)
            if values.shape != missing.shape:
                raise LoopClosureInputError(f"the scorer gave {values.shape} scores for {len(missing)} places")
            self.scored_last_step += len(missing)
            record.cache.update(zip(missing.tolist(), (float(v) - record.centre for v in values.tolist())))

    def reset(self) -> None:
        """Forget the recent queries: the next one starts a new sequence."""
        self._recent.clear()
        self._previous = None

    # ---- state, for checkpoints: plain arrays (no pickle), restored exactly -----------------
    def state_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """The recent queries (tokens must be arrays), their limits and score caches, and the
        previous query's best sequences, as named arrays that `load_state_arrays` restores."""
        out: dict[str, np.ndarray] = {f"{prefix}recent": np.array(len(self._recent), np.int64)}
        for i, query in enumerate(self._recent):
            places = np.fromiter(query.cache.keys(), np.int64, len(query.cache))
            out[f"{prefix}q{i}_token"] = np.asarray(query.token)
            out[f"{prefix}q{i}_limit"] = np.array(query.limit, np.int64)
            out[f"{prefix}q{i}_places"] = places
            out[f"{prefix}q{i}_scores"] = np.array([query.cache[p] for p in places.tolist()], np.float64)
            out[f"{prefix}q{i}_centre"] = np.array(query.centre, np.float64)
        if self._previous is not None:
            for direction, ranked in self._previous.items():
                out[f"{prefix}previous_{direction}"] = np.asarray(ranked, np.int64)
        return out

    @staticmethod
    def check_state_arrays(arrays: dict[str, np.ndarray], prefix: str, n_places: int) -> None:
        """Refuse saved arrays that would resume wrongly: NaN tokens or scores, places outside a
        map of `n_places` (LoopClosureInputError naming the array)."""
        for i in range(int(saved_ints(arrays, f"{prefix}recent", 0, 1 << 20))):
            saved_finite(arrays, f"{prefix}q{i}_token")
            saved_ints(arrays, f"{prefix}q{i}_limit", 0, n_places + 1)
            saved_ints(arrays, f"{prefix}q{i}_places", 0, max(n_places, 1))
            saved_finite(arrays, f"{prefix}q{i}_scores")
            if f"{prefix}q{i}_centre" in arrays:  # absent from states saved before centring: 0
                saved_finite(arrays, f"{prefix}q{i}_centre")
        for name in [n for n in arrays if n.startswith(f"{prefix}previous_")]:
            saved_ints(arrays, name, 0, n_places)

    def load_state_arrays(self, arrays: dict[str, np.ndarray], prefix: str = "") -> None:
        """Restore what `state_arrays` saved (into a matcher of the same configuration)."""
        self.reset()
        for i in range(int(arrays[f"{prefix}recent"])):
            places = arrays[f"{prefix}q{i}_places"].tolist()
            cache = dict(zip(places, arrays[f"{prefix}q{i}_scores"].tolist()))
            self._recent.append(
                _Query(np.array(arrays[f"{prefix}q{i}_token"]), int(arrays[f"{prefix}q{i}_limit"]), cache,
                       float(arrays.get(f"{prefix}q{i}_centre", 0.0)))
            )  # fmt: skip
        previous = {name.removeprefix(f"{prefix}previous_"): np.array(value, np.int64)
                    for name, value in arrays.items() if name.startswith(f"{prefix}previous_")}  # fmt: skip
        self._previous = previous or None
