"""loopclosure.frame_correlation: which places the RAS 2020 prior boosts."""

from __future__ import annotations

import numpy as np

from loopclosure.config import FrameCorrelationConfig
from loopclosure.frame_correlation import FrameCorrelationPrior


def _prior(**kw) -> FrameCorrelationPrior:
    return FrameCorrelationPrior(FrameCorrelationConfig(enabled=True, **kw))


def test_disabled_boosts_nothing():
    prior = FrameCorrelationPrior(FrameCorrelationConfig(enabled=False, history=3, radius=2))
    assert FrameCorrelationConfig().enabled is False  # the ECMR default
    for m in (10, 11, 12):
        prior.update(m)
    out = prior.boosted()
    assert out.shape == (0,) and out.dtype == np.int64


def test_nothing_boosted_before_a_recognition():
    prior = _prior()
    assert len(prior.boosted()) == 0
    prior.update(None)
    prior.update(None)
    assert len(prior.boosted()) == 0


def test_one_step_forward_with_radius():
    """Query t-1 matched m: query t probably matches m + 1, give or take the radius."""
    prior = _prior(history=1, radius=2)
    prior.update(40)
    np.testing.assert_array_equal(prior.boosted(), [39, 40, 41, 42, 43])


def test_history_two_shifts_each_match_by_its_age():
    prior = _prior(history=2, radius=1)
    prior.update(10)  # two steps ago -> centre 12
    prior.update(20)  # one step ago -> centre 21
    np.testing.assert_array_equal(prior.boosted(), [11, 12, 13, 20, 21, 22])


def test_consistent_track_gives_one_window():
    prior = _prior(history=3, radius=0)
    for m in (5, 6, 7):
        prior.update(m)
    np.testing.assert_array_equal(prior.boosted(), [8])


def test_old_matches_fall_out_of_the_history():
    prior = _prior(history=2, radius=0)
    prior.update(100)
    prior.update(200)
    prior.update(300)  # 100 is forgotten
    np.testing.assert_array_equal(prior.boosted(), [202, 301])


def test_failed_recognition_still_ages_the_history():
    prior = _prior(history=2, radius=0)
    prior.update(50)
    prior.update(None)
    np.testing.assert_array_equal(prior.boosted(), [52])
    prior.update(None)
    assert len(prior.boosted()) == 0


def test_reset_forgets_everything():
    prior = _prior(history=2, radius=1)
    prior.update(3)
    prior.reset()
    assert len(prior.boosted()) == 0
    prior.update(0)
    np.testing.assert_array_equal(prior.boosted(), [0, 1, 2])  # centre 0 + 1


def test_boosted_is_sorted_unique_int64():
    prior = _prior(history=4, radius=3)
    for m in (10, 12, 11, 13):
        prior.update(m)
    out = prior.boosted()
    assert out.dtype == np.int64
    assert np.array_equal(out, np.unique(out))
    centres = {13 + 1, 11 + 2, 12 + 3, 10 + 4}
    assert set(out.tolist()) == {c + r for c in centres for r in range(-3, 4)}


# ------------------------------------------------------------------- wrong lock and recovery


def test_unsupported_recognitions_boost_nothing_when_recovering():
    prior = _prior(history=2, radius=0)  # recover is on by default
    assert FrameCorrelationConfig().recover is True
    prior.update(10, supported=True)
    prior.update(30, supported=False)  # won only through the boost: not propagated
    np.testing.assert_array_equal(prior.boosted(), [12])
    released = _prior(history=2, radius=0, recover=False)  # the authors' prior
    released.update(10, supported=True)
    released.update(30, supported=False)
    np.testing.assert_array_equal(released.boosted(), [12, 31])


def _partial_copy(grid: np.ndarray, rows: int, rng: np.random.Generator) -> np.ndarray:
    """A grid that shares its first `rows` rows with `grid`: a weak but real stage-II match."""
    out = rng.standard_normal(grid.shape).astype(np.float32)
    out[:rows] = grid[:rows]
    return out


def _stream(recover: bool) -> list[int]:
    """Queries 0..7 are places 10..17 exactly; then the stream jumps to places 40.. and the
    queries only weakly resemble them (stage-II score ~0.3 against a boost of 0.5)."""
    from loopclosure.config import VPRConfig
    from loopclosure.database import PlaceDatabase
    from loopclosure.encoder import PlaceCodes
    from loopclosure.pca import Codebooks, PCAProjection
    from loopclosure.two_stage import TwoStageRanker

    rng = np.random.default_rng(0)
    n, d = 60, 16
    pca = PCAProjection(np.zeros(4, np.float32), np.zeros((d, 4), np.float32), np.ones(d, np.float32), False, False)
    stage1 = rng.standard_normal((n, 16, d)).astype(np.float32)
    stage1 /= np.linalg.norm(stage1, axis=-1, keepdims=True)
    stage2 = rng.standard_normal((n, 13, 13, d)).astype(np.float32)
    config = VPRConfig.model_validate({"filtering": {"num_candidates": 10}, "database": {"stage2_dtype": "float32"},
                                       "frame_correlation": {"enabled": True, "recover": recover}})  # fmt: skip
    db = PlaceDatabase(Codebooks(pca, pca), config.database)
    db.add(PlaceCodes(stage1, stage2))
    places = list(range(10, 18)) + list(range(40, 52))
    queries = [PlaceCodes(stage1[p][None], (stage2[p] if i < 8 else _partial_copy(stage2[p], 5, rng))[None])
               for i, p in enumerate(places)]  # fmt: skip
    recognizer, prior, matches = TwoStageRanker(config, db), FrameCorrelationPrior(config.frame_correlation), []
    for q in queries:
        rec = recognizer.query(q, boosted=prior.boosted())
        prior.update(rec.best_place, rec.won_without_boost)
        matches.append(rec.best_place)
    return [m - p for m, p in zip(matches, places)]


def test_the_released_prior_locks_onto_the_wrong_places_after_a_jump():
    errors = _stream(recover=False)
    assert errors[:8] == [0] * 8
    assert all(abs(e) > 2 for e in errors[8:])  # never recovers: the boosted neighbours win every query


def test_with_recovery_a_wrong_lock_dies_after_history_queries():
    errors = _stream(recover=True)
    assert errors[:8] == [0] * 8
    assert all(e == 0 for e in errors[8 + 2 :])  # history = 2: two boosted misses, then the evidence wins
