"""loopclosure.filtering.vote: stage-I histogram voting on hand-built databases."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from loopclosure.filtering import Candidates, vote


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def _clustered_query(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    """n unit vectors all close to e0, so every one of them is nearer to each other than to noise."""
    base = np.zeros((n, d), np.float32)
    base[:, 0] = 1.0
    return _unit(base + 0.05 * rng.standard_normal((n, d)))


def _far_places(rng: np.random.Generator, p: int, n: int, d: int) -> np.ndarray:
    """Places whose vectors point away from e0 (negative first coordinate)."""
    x = rng.standard_normal((p, n, d))
    x[..., 0] = -np.abs(x[..., 0]) - 1.0
    return _unit(x)


def test_copy_of_query_gets_all_votes_and_score_one():
    rng = np.random.default_rng(0)
    n, d, p = 16, 12, 8
    query = _clustered_query(rng, n, d)
    db = _far_places(rng, p, n, d)
    db[3] = query[rng.permutation(n)]  # same vectors, stored in another order
    for k in (n, n + 5):  # k >= per_place: each query vector's top n are exactly place 3's vectors
        c = vote(query, db, k_neighbours=k, num_candidates=4)
        assert c.places[0] == 3
        assert c.votes[0] == n * n
        assert c.scores[0] == pytest.approx(1.0)
        assert (c.scores[1:] < 1.0).all()


def test_score_normalisation_with_k_below_per_place():
    rng = np.random.default_rng(1)
    n, d = 4, 10
    query = _clustered_query(rng, n, d)
    db = _far_places(rng, 5, n, d)
    db[2] = query
    c = vote(query, db, k_neighbours=2, num_candidates=5)
    # every neighbour lies in place 2: n * k votes out of a possible n * min(k, per_place)
    np.testing.assert_array_equal(c.places, [2])
    np.testing.assert_array_equal(c.votes, [n * 2])
    np.testing.assert_allclose(c.scores, [1.0])


def test_excluded_place_never_returned_even_if_best():
    rng = np.random.default_rng(2)
    n, d, p = 8, 10, 6
    query = _clustered_query(rng, n, d)
    db = _far_places(rng, p, n, d)
    db[1] = query
    db[4] = _unit(query + 0.2 * rng.standard_normal(query.shape))
    assert vote(query, db, 8, 3).places[0] == 1
    c = vote(query, db, 8, 3, excluded=np.array([1]))
    assert 1 not in c.places
    assert c.places[0] == 4
    # all but one excluded: only that one can come back
    c = vote(query, db, 8, 3, excluded=np.array([0, 1, 2, 4, 5]))
    np.testing.assert_array_equal(c.places, [3])


def test_exclusion_happens_before_choosing_neighbours():
    """Ten excluded near-duplicates would fill every query vector's k neighbours; the true
    place must still be found, which is only possible if they are removed first."""
    rng = np.random.default_rng(3)
    n, d = 4, 16
    query = _clustered_query(rng, n, d)
    db = _far_places(rng, 30, n, d)
    excluded = np.arange(10, 20)
    for e in excluded:
        db[e] = _unit(query + 0.001 * rng.standard_normal(query.shape))  # the recent past
    true_place = 25
    db[true_place] = _unit(query + 0.1 * rng.standard_normal(query.shape))
    k, n_cand = 8, 3
    # control: without exclusion the recent past crowds the true place out entirely
    crowded = vote(query, db, k, n_cand)
    assert true_place not in crowded.places
    assert set(crowded.places) <= set(excluded)
    c = vote(query, db, k, n_cand, excluded=excluded)
    assert c.places[0] == true_place
    assert not set(c.places) & set(excluded)
    assert c.votes[0] == n * n  # each query vector finds all n of the true place's vectors first


def test_num_candidates_respected_and_order_by_votes():
    rng = np.random.default_rng(4)
    n, d, p = 6, 8, 40
    query = _unit(rng.standard_normal((n, d)))
    db = _unit(rng.standard_normal((p, n, d)))
    full = vote(query, db, 20, p)
    assert 17 < len(full) < p  # 120 neighbours spread over most, not all, places
    for n_cand in (1, 5, 17):
        c = vote(query, db, k_neighbours=20, num_candidates=n_cand)
        assert len(c) == n_cand
        assert len(set(c.places)) == len(c)
        assert (np.diff(c.votes) <= 0).all()
        np.testing.assert_array_equal(c.places, full.places[:n_cand])
    assert len(vote(query, db, 20, 10 * p)) == len(full)


def test_votes_agree_with_brute_force_count():
    rng = np.random.default_rng(5)
    n, d, p, k = 5, 6, 12, 7
    query = _unit(rng.standard_normal((n, d)))
    db = _unit(rng.standard_normal((p, 3, d)))
    sims = query @ db.reshape(-1, d).T
    expected = np.zeros(p, int)
    for row in sims:
        for idx in np.argsort(-row)[:k]:
            expected[idx // 3] += 1
    c = vote(query, db, k, p)
    got = np.zeros(p, int)
    got[c.places] = c.votes
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_allclose(c.scores, c.votes / (n * 3))


def test_ties_in_votes_broken_by_summed_similarity():
    d = 4
    q = np.array([[1.0, 0, 0, 0]], np.float32)

    def at(cos: float) -> np.ndarray:
        return np.array([cos, np.sqrt(1 - cos**2), 0, 0], np.float32)

    db = np.stack([[at(0.5)], [at(0.9)], [at(0.7)], [at(-0.9)]])  # one vector per place
    c = vote(q, db, k_neighbours=3, num_candidates=4)
    np.testing.assert_array_equal(c.places, [1, 2, 0])
    np.testing.assert_array_equal(c.votes, [1, 1, 1])
    # more votes beat a higher similarity: place 0 has two weak vectors, place 1 one strong
    db2 = np.stack([[at(0.3), at(0.31)], [at(0.99), at(-1.0)], [at(-0.5), at(-0.6)]])
    c = vote(q, db2, k_neighbours=3, num_candidates=3)
    np.testing.assert_array_equal(c.places, [0, 1])
    np.testing.assert_array_equal(c.votes, [2, 1])
    assert db.shape[-1] == d


def test_empty_and_all_excluded_return_empty_candidates():
    rng = np.random.default_rng(6)
    query = _unit(rng.standard_normal((3, 5)))
    db = _unit(rng.standard_normal((4, 3, 5)))
    c = vote(query, db, 5, 3, excluded=np.arange(4))
    assert isinstance(c, Candidates) and len(c) == 0
    assert c.places.shape == c.votes.shape == c.scores.shape == (0,)
    c = vote(query, np.empty((0, 3, 5), np.float32), 5, 3)
    assert len(c) == 0


def test_query_dimension_mismatch_refused():
    with pytest.raises(ValueError, match="stage-I query"):
        vote(np.zeros((3, 4), np.float32), np.zeros((2, 3, 5), np.float32), 2, 2)
    with pytest.raises(ValueError, match="stage-I query"):
        vote(np.zeros((5,), np.float32), np.zeros((2, 3, 5), np.float32), 2, 2)


def test_float16_database_votes_like_float32():
    rng = np.random.default_rng(7)
    query = _clustered_query(rng, 6, 8)
    db = _far_places(rng, 10, 6, 8)
    db[7] = query
    c16 = vote(query, db.astype(np.float16), 6, 3)
    c32 = vote(query, db, 6, 3)
    assert c16.places[0] == c32.places[0] == 7
    assert c16.votes[0] == c32.votes[0]


@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(1, 8),
    per_place=st.integers(1, 6),
    places=st.integers(1, 12),
    d=st.integers(1, 6),
    k=st.integers(1, 40),
    data=st.data(),
)
@settings(max_examples=150, deadline=None)
def test_vote_properties(seed, n, per_place, places, d, k, data):
    rng = np.random.default_rng(seed)
    query = rng.standard_normal((n, d)).astype(np.float32)
    db = rng.standard_normal((places, per_place, d)).astype(np.float32)
    excluded = np.array(data.draw(st.lists(st.integers(0, places - 1), max_size=places, unique=True)), np.int64)
    n_allowed = places - len(excluded)
    c = vote(query, db, k, num_candidates=places, excluded=excluded)
    if n_allowed == 0:
        assert len(c) == 0
        return
    k_eff = min(k, n_allowed * per_place)
    assert c.votes.sum() == n * k_eff
    assert (c.votes >= 1).all()
    assert (c.votes <= n * min(k_eff, per_place)).all()
    assert (c.scores >= 0).all() and (c.scores <= 1).all()
    np.testing.assert_allclose(c.scores, c.votes / (n * min(k_eff, per_place)), rtol=1e-6)
    assert not set(c.places.tolist()) & set(excluded.tolist())
    assert len(set(c.places.tolist())) == len(c)
    assert (np.diff(c.votes) <= 0).all()
