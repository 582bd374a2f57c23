"""Sequence matching on synthetic stage-II score matrices: forward and reverse revisits, speed
changes, broken sequences, start-up with fewer than L predecessors, database edges, exclusion
limits, and the streaming matcher giving exactly the batch result.

A score matrix S[q, r] stands for the stage-II scores of query q against place r: background
noise in [0, 0.3], revisits planted as lines of high scores.
"""

from __future__ import annotations

import numpy as np
import pytest

from loopclosure.config import SequenceMatchConfig
from loopclosure.errors import LoopClosureInputError
from loopclosure.metrics import pr_auc, precision_recall_curve
from loopclosure.sequence_matcher import SequenceMatch, SequenceMatcher, match_sequences, offsets


def noise(n_query: int, n_places: int, seed: int = 0, high: float = 0.3) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, high, (n_query, n_places)).astype(np.float32)


def plant(s: np.ndarray, queries: range, places: list[int] | np.ndarray, value: float = 0.8) -> np.ndarray:
    for q, r in zip(queries, places):
        s[q, r] = value
    return s


def cfg(**kw: object) -> SequenceMatchConfig:
    return SequenceMatchConfig(**kw)


class MatrixScorer:
    """A scorer over a dense matrix that counts what it is asked (token = query index)."""

    def __init__(self, s: np.ndarray) -> None:
        self.s = s
        self.asked: list[tuple[int, int]] = []

    def __call__(self, token: int, places: np.ndarray) -> np.ndarray:
        self.asked += [(token, int(p)) for p in places]
        return self.s[token, places]


def stream(
    s: np.ndarray,
    config: SequenceMatchConfig,
    candidates: list[np.ndarray] | None = None,
    limits: np.ndarray | None = None,
    scorer: MatrixScorer | None = None,
) -> list[SequenceMatch]:
    """The streaming matcher driven as the detector drives it: continuations scored with the candidates."""
    n_query, n_places = s.shape
    scorer = scorer or MatrixScorer(s)
    matcher = SequenceMatcher(config, scorer)
    out = []
    for q in range(n_query):
        limit = n_places if limits is None else int(limits[q])
        places = np.arange(limit) if candidates is None else candidates[q]
        extra = matcher.continuations(limit)
        out.append(matcher.step(q, places, s[q, places], limit, extra, s[q, extra]))
    return out


def assert_same(a: SequenceMatch, b: SequenceMatch) -> None:
    assert (a.place, a.direction, a.speed, a.terms) == (b.place, b.direction, b.speed, b.terms)
    assert a.score == b.score and a.single_score == b.single_score
    np.testing.assert_array_equal(a.candidates, b.candidates)
    np.testing.assert_array_equal(a.candidate_scores, b.candidate_scores)


def auc(
    matches: list[SequenceMatch] | np.ndarray, scores: np.ndarray | None, truth: dict[int, int], tol: int = 1
) -> float:
    if scores is None:
        places = np.array([-1 if m.place is None else m.place for m in matches])
        scores = np.array([m.score for m in matches])
    else:
        places = np.asarray(matches)
    n = len(places)
    has = np.array([q in truth for q in range(n)])
    correct = np.array([q in truth and abs(places[q] - truth[q]) <= tol for q in range(n)])
    return pr_auc(precision_recall_curve(scores, correct, has))


# --------------------------------------------------------------------------------- definition


def test_scores_and_limits_of_the_wrong_shape_are_input_errors() -> None:
    with pytest.raises(LoopClosureInputError, match=r"\(queries, places\) matrix, got shape \(5,\)"):
        match_sequences(np.zeros(5), cfg(length=3))
    with pytest.raises(LoopClosureInputError, match="limits must be 4 place counts in 0..6"):
        match_sequences(np.zeros((4, 6)), cfg(length=3), limits=np.array([1, 2, 3, 7]))
    with pytest.raises(LoopClosureInputError, match="limits must be 4 place counts"):
        match_sequences(np.zeros((4, 6)), cfg(length=3), limits=np.array([1, 2]))


def test_forward_revisit_scores_the_mean_of_its_diagonal() -> None:
    s = plant(noise(40, 60), range(20, 30), list(range(5, 15)))
    res = match_sequences(s, cfg(length=3))
    for q in range(22, 30):
        m = res[q]
        assert m.place == q - 15 and m.direction == "forward" and m.terms == 3
        assert m.score == pytest.approx(0.8)
        assert m.single_score == pytest.approx(0.8)


def test_reverse_revisit_found_only_when_reverse_is_allowed() -> None:
    s = plant(noise(40, 60), range(20, 30), list(range(45, 35, -1)))
    both = match_sequences(s, cfg(length=3, direction="both"))
    forward = match_sequences(s, cfg(length=3, direction="forward"))
    for q in range(22, 30):
        assert both[q].place == 65 - q and both[q].direction == "reverse"
        assert both[q].score == pytest.approx(0.8)
        assert forward[q].score < 0.5  # the forward line through the reverse revisit is mostly noise
    reverse = match_sequences(s, cfg(length=3, direction="reverse"))
    assert [m.place for m in reverse[22:30]] == [m.place for m in both[22:30]]


def test_a_single_frame_alias_loses_to_a_sequence() -> None:
    # query 27 sees a brighter alias at place 50 than its true place 12
    s = plant(noise(40, 60), range(20, 30), list(range(5, 15)), value=0.6)
    s[27, 50] = 0.9
    assert int(np.argmax(s[27])) == 50  # single frame: wrong
    m = match_sequences(s, cfg(length=3))[27]
    assert m.place == 12 and m.score == pytest.approx(0.6)


def test_speed_change_needs_a_slope() -> None:
    # the revisit is driven at half the speed: one place every two queries
    places = [10 + k // 2 for k in range(16)]
    s = plant(noise(40, 60, seed=1), range(20, 36), places)
    straight = match_sequences(s, cfg(length=5))
    sloped = match_sequences(s, cfg(length=5, speeds=[0.5, 1.0]))
    for q in range(24, 36):
        assert sloped[q].place == places[q - 20] and sloped[q].speed == 0.5
        assert straight[q].score < sloped[q].score  # the unit slope meets the line only in part
        if (q - 20) % 2 == 0:  # rounded offsets 0,1,1,2,2 follow the line in this phase exactly
            assert sloped[q].score == pytest.approx(0.8) and straight[q].score < 0.6


@pytest.mark.parametrize("speed", [0.5, 0.75, 1.0, 1.25, 2.0])
def test_offsets_round_half_up(speed: float) -> None:
    got = offsets(cfg(length=5), speed)
    assert got[0] == 0 and list(got) == [int(np.floor(speed * k + 0.5)) for k in range(5)]


def test_broken_sequence_rises_again_after_the_break() -> None:
    # a revisit interrupted for two queries (an occlusion): the break lowers the score, the
    # sequence recovers L queries after it
    s = plant(noise(50, 60, seed=2), range(20, 40), list(range(5, 25)))
    s[30, 15] = s[31, 16] = 0.05
    res = match_sequences(s, cfg(length=3))
    assert res[29].score == pytest.approx(0.8)
    assert res[32].score == pytest.approx((0.8 + 0.05 + 0.05) / 3) or res[32].place != 17
    assert res[34].place == 19 and res[34].score == pytest.approx(0.8)


def test_start_up_aggregates_what_exists_counting_missing_terms_as_zero() -> None:
    s = noise(10, 20, seed=3)
    s[0, 7], s[1, 8], s[2, 9] = 0.9, 0.9, 0.9
    res = match_sequences(s, cfg(length=3))
    assert res[0].place == 7 and res[0].terms == 1 and res[0].score == pytest.approx(0.9 / 3)
    assert res[1].place == 8 and res[1].terms == 2 and res[1].score == pytest.approx(1.8 / 3)
    assert res[2].place == 9 and res[2].terms == 3 and res[2].score == pytest.approx(0.9)
    skip = match_sequences(s, cfg(length=3, missing="skip"))
    assert skip[0].score == pytest.approx(0.9) and skip[1].score == pytest.approx(0.9)


def test_database_edges_are_missing_terms() -> None:
    s = noise(10, 20, seed=4)
    s[5, 1], s[4, 0] = 0.9, 0.9  # forward: place 1 at query 5 has only places 1 and 0 behind it
    m = match_sequences(s, cfg(length=4), candidates=[np.array([1])] * 10)[5]
    assert m.place == 1 and m.terms == 2 and m.score == pytest.approx(1.8 / 4)
    s[5, 18], s[4, 19] = 0.9, 0.9  # reverse at the last place
    m = match_sequences(s, cfg(length=4, direction="reverse"), candidates=[np.array([18])] * 10)[5]
    assert m.place == 18 and m.terms == 2 and m.score == pytest.approx(1.8 / 4)


def test_a_place_the_earlier_query_could_not_match_is_a_missing_term() -> None:
    # a U-turn: query 12 drives back over places 11, 10, ...; its predecessors must not be
    # credited with matching themselves (the places inside their exclusion window)
    s = noise(20, 20, seed=5)
    for q in range(20):
        s[q, q] = 1.0  # every query is identical to its own place
    limits = np.maximum(np.arange(20) - 3, 0)  # the last 3 places are excluded
    res = match_sequences(s, cfg(length=3, direction="reverse"), limits=limits)
    for m in res[4:]:
        assert m.place is not None and m.score < 0.5  # no self-match leaks in through the terms


def test_length_one_is_single_frame_recognition() -> None:
    s = noise(30, 40, seed=6)
    rng = np.random.default_rng(0)
    cands = [rng.choice(40, 10, replace=False) for _ in range(30)]
    for m, q in zip(match_sequences(s, cfg(length=1, direction="both"), cands), range(30)):
        best = cands[q][np.argmax(s[q, cands[q]])]
        assert m.place == best and m.score == pytest.approx(float(s[q, best])) and m.terms == 1
        assert len(m.candidates) == 10  # no continuations at L = 1


def test_continuation_finds_the_place_stage_one_missed() -> None:
    s = plant(noise(30, 50, seed=7), range(10, 20), list(range(30, 40)))
    cands = [np.array([0, 1, 2]) if q == 15 else np.arange(50) for q in range(30)]  # stage I misses at 15
    res = match_sequences(s, cfg(length=3), cands)
    assert res[15].place == 35 and res[15].score == pytest.approx(0.8)
    assert stream(s, cfg(length=3), cands)[15].place == 35


def test_no_candidates_gives_no_match_and_the_stream_goes_on() -> None:
    s = plant(noise(10, 30, seed=8), range(0, 10), list(range(10, 20)))
    cands = [np.arange(30) if q != 4 else np.empty(0, np.int64) for q in range(10)]
    for res in (
        match_sequences(s, cfg(length=3, continuations=0), cands),
        stream(s, cfg(length=3, continuations=0), cands),
    ):
        assert res[4].place is None and res[4].direction is None
        assert res[6].place == 16 and res[6].score == pytest.approx(0.8)


# ------------------------------------------------------------------------ streaming == batch


CONFIGS = [
    cfg(length=1),
    cfg(length=2),
    cfg(length=3, direction="both"),
    cfg(length=5),
    cfg(length=5, direction="reverse", continuations=1),
    cfg(length=4, speeds=[0.75, 1.0, 1.25], direction="both"),
    cfg(length=5, sequence_candidates=5),
    cfg(length=5, sequence_candidates=None),
    cfg(length=3, direction="both", sequence_candidates=None),
    cfg(length=3, missing="skip"),
    cfg(length=5, aggregation="median"),
    cfg(length=5, aggregation="median", missing="skip", speeds=[0.5, 1.0, 2.0]),
]


@pytest.mark.parametrize(
    "config", CONFIGS, ids=lambda c: f"L{c.length}-{c.direction}-{c.aggregation}-{c.missing}-{len(c.speeds)}v"
)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_streaming_equals_batch(config: SequenceMatchConfig, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n_query, n_places = 60, 80
    s = noise(n_query, n_places, seed)
    plant(s, range(10, 30), list(range(20, 40)), 0.7)
    plant(s, range(35, 50), list(range(70, 55, -1)), 0.7)
    plant(s, range(50, 60), [5 + k // 2 for k in range(10)], 0.7)
    cands = [rng.choice(n_places, 12, replace=False) for _ in range(n_query)]  # stage I in its own order
    limits = np.minimum(n_places, 40 + np.arange(n_query) // 2)  # a growing database, as in SLAM
    scorer = MatrixScorer(s)
    batch = match_sequences(s, config, cands, limits)
    streamed = stream(s, config, cands, limits, scorer)
    for a, b in zip(streamed, batch):
        assert_same(a, b)
    # every (query, place) pair was scored at most once, and never beyond what the query could match
    assert len(scorer.asked) == len(set(scorer.asked))
    assert all(p < limits[q] for q, p in scorer.asked)


class BatchCounter:
    """A batch scorer over a MatrixScorer that counts its calls."""

    def __init__(self, scorer: MatrixScorer) -> None:
        self.scorer, self.calls = scorer, 0

    def __call__(self, wanted: list[tuple[int, np.ndarray]]) -> list[np.ndarray]:
        self.calls += 1
        return [self.scorer(token, places) for token, places in wanted]


@pytest.mark.parametrize("config", [CONFIGS[3], CONFIGS[5], CONFIGS[11]], ids=["L5", "L4-3v-both", "L5-median"])
def test_a_batch_scorer_scores_the_earlier_queries_in_one_call_with_the_same_result(
    config: SequenceMatchConfig,
) -> None:
    """On a GPU the terms of all earlier queries of a step are scored in one device call; the
    matches must be those of one call per query, and no pair scored twice."""
    rng = np.random.default_rng(4)
    s = noise(50, 70, 4)
    plant(s, range(10, 30), list(range(20, 40)), 0.7)
    cands = [rng.choice(70, 12, replace=False) for _ in range(50)]
    limits = np.minimum(70, 30 + np.arange(50))
    one_by_one = stream(s, config, cands, limits)
    scorer = MatrixScorer(s)
    batch = BatchCounter(scorer)
    matcher = SequenceMatcher(config, scorer, batch_scorer=batch)
    steps_with_terms = 0
    for q in range(50):
        limit = int(limits[q])
        extra = matcher.continuations(limit)
        asked = len(scorer.asked)
        calls = batch.calls
        match = matcher.step(q, cands[q], s[q, cands[q]], limit, extra, s[q, extra])
        assert_same(match, one_by_one[q])
        assert batch.calls - calls <= 1  # never more than one batch a step
        steps_with_terms += len(scorer.asked) > asked
    assert batch.calls >= steps_with_terms - 2 > 0  # the first steps have at most one earlier query
    assert len(scorer.asked) == len(set(scorer.asked))


@pytest.mark.parametrize("k", [None, 10])
def test_streaming_cost_is_about_length_times_candidates(k: int | None) -> None:
    s = noise(100, 500, seed=9)
    plant(s, range(40, 100), list(range(100, 160)))
    rng = np.random.default_rng(1)
    cands = [rng.choice(500, 50, replace=False) for _ in range(100)]
    scorer = MatrixScorer(s)
    config = cfg(length=5, continuations=3, sequence_candidates=k)
    matcher = SequenceMatcher(config, scorer)
    costs = []
    for q in range(100):
        extra = matcher.continuations(500)
        before = len(scorer.asked)
        matcher.step(q, cands[q], s[q, cands[q]], 500, extra, s[q, extra])
        costs.append(len(scorer.asked) - before)
        # the past L-1 queries' terms for the K (or N) candidates and the continued places
        assert costs[-1] <= (config.length - 1) * ((k or 50) + 3)
    assert max(costs[50:]) <= (config.length - 1) * ((k or 50) + 3)


def test_reset_starts_a_new_sequence() -> None:
    s = plant(noise(20, 30), range(0, 20), list(range(5, 25)))
    matcher = SequenceMatcher(cfg(length=3), MatrixScorer(s))
    for q in range(5):
        m = matcher.step(q, np.arange(30), s[q], 30)
    assert m.terms == 3
    matcher.reset()
    m = matcher.step(5, np.arange(30), s[5], 30)
    assert m.terms == 1 and len(matcher.continuations(30)) == 0 or m.place == 10


def test_mismatched_scores_are_refused() -> None:
    matcher = SequenceMatcher(cfg(length=2), MatrixScorer(noise(3, 3)))
    with pytest.raises(ValueError, match="places but"):
        matcher.step(0, np.arange(3), np.zeros(2), 3)


@pytest.mark.parametrize("bad", [[0.0], [-1.0], [1.0, 5.0]])
def test_config_refuses_bad_speeds(bad: list[float]) -> None:
    with pytest.raises(ValueError):
        cfg(speeds=bad)


# -------------------------------------------------------------------------- never worse


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("length", [2, 3, 5])
def test_sequence_auc_is_not_below_single_frame_auc(seed: int, length: int) -> None:
    """A revisit (with truth) inside a stream that also has unrelated stretches (no truth),
    and single-frame aliases everywhere: the sequence ranks the stream at least as well."""
    rng = np.random.default_rng(seed)
    s = noise(120, 150, seed, high=0.45)
    truth = {q: q - 10 for q in range(30, 100)}
    for q, r in truth.items():
        s[q, r] = rng.uniform(0.35, 0.75)
    for q in rng.choice(120, 25, replace=False):  # bright aliases
        s[q, rng.integers(150)] = rng.uniform(0.5, 0.8)
    single_places = s.argmax(axis=1)
    single = auc(single_places, s.max(axis=1), truth)
    sequence = auc(match_sequences(s, cfg(length=length)), None, truth)
    assert sequence >= single, (single, sequence)


# --------------------------------------------------------------------- centres and seams


def stream_with_seams(
    s: np.ndarray,
    config: SequenceMatchConfig,
    candidates: list[np.ndarray],
    limits: np.ndarray,
    centres: np.ndarray,
    place_segments: np.ndarray,
    query_segments: np.ndarray,
) -> list[SequenceMatch]:
    """The streaming matcher as the detector drives it across seams: reset where a new stretch
    of queries begins, places told their stretch, every query's scores centred."""
    matcher = SequenceMatcher(config, MatrixScorer(s), lambda places: place_segments[places])
    out = []
    for q in range(s.shape[0]):
        if q and query_segments[q] != query_segments[q - 1]:
            matcher.reset()
        limit, places = int(limits[q]), candidates[q]
        extra = matcher.continuations(limit)
        out.append(matcher.step(q, places, s[q, places], limit, extra, s[q, extra], float(centres[q])))
    return out


@pytest.mark.parametrize("config", CONFIGS[:8], ids=lambda c: f"L{c.length}-{c.direction}-{len(c.speeds)}v")
@pytest.mark.parametrize("seed", [0, 1])
def test_streaming_equals_batch_with_centres_and_seams(config: SequenceMatchConfig, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n_query, n_places = 60, 80
    s = noise(n_query, n_places, seed)
    plant(s, range(10, 30), list(range(20, 40)), 0.7)
    plant(s, range(35, 50), list(range(70, 55, -1)), 0.7)
    cands = [rng.choice(n_places, 12, replace=False) for _ in range(n_query)]
    limits = np.minimum(n_places, 40 + np.arange(n_query) // 2)
    centres = rng.uniform(0.0, 0.2, n_query)
    place_segments = (np.arange(n_places) >= 30).astype(np.int64) + (np.arange(n_places) >= 62)
    query_segments = (np.arange(n_query) >= 25).astype(np.int64)
    batch = match_sequences(s, config, cands, limits, centres, place_segments, query_segments)
    streamed = stream_with_seams(s, config, cands, limits, centres, place_segments, query_segments)
    for a, b in zip(streamed, batch):
        assert_same(a, b)


def test_a_sequence_does_not_run_across_a_seam_between_stretches_of_places() -> None:
    # queries 0..9 match places 10..19 on a line; places 14 and 15 lie on different stretches
    # (say the end of a first traverse and the start of a second), so the line to place 17
    # counts only the terms from 15 on
    s = plant(noise(10, 30, high=0.0), range(10), list(range(10, 20)), 0.9)
    config = cfg(length=5, sequence_candidates=None, continuations=0)
    whole = match_sequences(s, config)
    seams = match_sequences(s, config, place_segments=(np.arange(30) >= 15).astype(np.int64))
    assert whole[7].place == 17 and whole[7].terms == 5 and whole[7].score == pytest.approx(0.9)
    assert seams[7].place == 17 and seams[7].terms == 3 and seams[7].score == pytest.approx(0.9 * 3 / 5)


def test_centring_subtracts_each_query_s_own_level_from_its_terms() -> None:
    s = plant(noise(6, 20, high=0.0), range(6), list(range(6)), 0.5)
    centres = np.array([0.1, 0.2, 0.3, 0.0, 0.0, 0.4])
    config = cfg(length=3, sequence_candidates=None, continuations=0)
    out = match_sequences(s, config, centres=centres)
    # query 5 -> place 5: terms (0.5 - 0.4) + (0.5 - 0) + (0.5 - 0), over L = 3
    assert out[5].place == 5 and out[5].score == pytest.approx((0.1 + 0.5 + 0.5) / 3)
    assert out[5].single_score == pytest.approx(0.1)


def test_a_centre_that_is_not_finite_is_refused() -> None:
    matcher = SequenceMatcher(cfg(length=2), MatrixScorer(noise(3, 3)))
    with pytest.raises(ValueError, match="centre"):
        matcher.step(0, np.arange(3), np.zeros(3), 3, centre=float("nan"))
