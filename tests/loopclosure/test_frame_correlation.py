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
