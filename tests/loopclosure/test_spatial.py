"""loopclosure.spatial: the vectorised closed form against the paper's literal loop."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from loopclosure import spatial
from loopclosure.spatial import (
    as_float32,
    best_query_cells,
    consistency_counts,
    max_raw_score,
    spatial_score_literal,
    spatial_scores,
)
from loopclosure.spatial_torch import spatial_scores_torch, spatial_scores_torch_many, stage2_scores


@st.composite
def grids(draw):
    gh = draw(st.integers(2, 6))
    gw = draw(st.integers(2, 6))
    d = draw(st.integers(1, 6))
    c = draw(st.integers(1, 4))
    ints = st.integers(-3, 3)
    query = draw(arrays(np.int8, (gh, gw, d), elements=ints)).astype(np.float32)
    cands = draw(arrays(np.int8, (c, gh, gw, d), elements=ints)).astype(np.float32)
    return query, cands


@given(grids())
@settings(max_examples=150, deadline=None)
def test_closed_form_equals_literal_algorithm(grid):
    """Small integer codes make every distance exact, so ties resolve to the first minimum in both."""
    query, cands = grid
    gh, gw, _ = query.shape
    result = spatial_scores(query, cands)
    expected = [spatial_score_literal(query, cand) for cand in cands]
    np.testing.assert_array_equal(result.raw, expected)
    np.testing.assert_allclose(result.scores, np.asarray(expected) / max_raw_score(gh, gw), rtol=1e-6)
    assert (result.scores >= 0).all() and (result.scores <= 1).all()
    assert result.shifts.shape == (len(cands), 2)
    assert (np.abs(result.shifts[:, 0]) < gh).all() and (np.abs(result.shifts[:, 1]) < gw).all()


@given(grids(), st.integers(1, 3))
@settings(max_examples=30, deadline=None)
def test_chunking_changes_nothing(grid, chunk):
    query, cands = grid
    a = spatial_scores(query, cands, chunk=chunk)
    b = spatial_scores(query, cands)
    np.testing.assert_array_equal(a.raw, b.raw)
    np.testing.assert_array_equal(a.scores, b.scores)
    np.testing.assert_array_equal(a.shifts, b.shifts)


def _unique_grid(gh: int, gw: int, d: int = 8, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal((gh, gw, d)).astype(np.float32)


def test_literal_reference_on_identity_is_the_maximum():
    q = _unique_grid(4, 5)
    assert spatial_score_literal(q, q) == max_raw_score(4, 5) == 4 * 5 * 5 + 5 * 4 * 4


def test_identical_candidate_scores_one_with_zero_shift():
    q = _unique_grid(13, 13, d=100)
    r = spatial_scores(q, q[None])
    assert r.raw[0] == max_raw_score(13, 13)
    assert r.scores[0] == pytest.approx(1.0)
    np.testing.assert_array_equal(r.shifts[0], [0, 0])


def test_translated_candidate_has_the_translation_as_dominant_shift():
    """Candidate cell (i, j) holds query cell (i, j + 2) (the grid rolled left by two columns,
    wrapping). Its best query cell is (i, j + 2), so best - cell = (0, +2) for the gw - 2
    columns that did not wrap and (0, -(gw - 2)) for the two that did."""
    gh, gw = 7, 9
    q = _unique_grid(gh, gw)
    cand = np.roll(q, -2, axis=1)
    assert np.array_equal(cand[3, 4], q[3, 6])
    r = spatial_scores(q, cand[None])
    np.testing.assert_array_equal(r.shifts[0], [0, 2])
    # rows: groups of gw-2 and 2 cells; columns: one displacement each
    expected = gh * ((gw - 2) ** 2 + 2**2) + gw * gh**2
    assert r.raw[0] == expected == spatial_score_literal(q, cand)

    down = np.roll(q, 3, axis=0)  # candidate (i, j) holds query (i - 3, j): shift (-3, 0)
    r = spatial_scores(q, down[None])
    np.testing.assert_array_equal(r.shifts[0], [-3, 0])


def test_best_query_cells_is_nearest_in_l2_not_dot_product():
    """A long vector has the largest dot product but is not the nearest."""
    q = np.array([[[1.0, 0.0], [10.0, 0.0]]], np.float32)  # 1x2 grid
    cand = np.array([[[[1.1, 0.0], [9.0, 0.0]]]], np.float32)
    np.testing.assert_array_equal(best_query_cells(q, cand), [[[0, 1]]])


def test_consistency_counts_on_hand_made_best_map():
    # 2x3 grid: flat best-cell indices; displacements (row, col):
    # row 0: cells -> (0,0),(0,1),(0,2): best 0,1,2 -> all (0,0)
    # row 1: cells -> best 0 (=(0,0): disp (-1,0)), 4 (=(1,1): (0,0)), 2 (=(0,2): (-1,0))
    best = np.array([[[0, 1, 2], [0, 4, 2]]])
    raw, shifts = consistency_counts(best)
    # rows: 3^2 + (2^2 + 1^2) = 14; columns: col0 {(0,0),(-1,0)} 1+1, col1 {(0,0),(0,0)} 4, col2 1+1 -> 8
    assert raw[0] == 22
    np.testing.assert_array_equal(shifts[0], [0, 0])  # 4 of 6 cells share (0, 0)
    assert spatial_score_literal(*_grids_for_best(best[0])) == 22


def _grids_for_best(best: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Query with one-hot cells and a candidate whose cell (i, j) copies query cell best[i, j]."""
    gh, gw = best.shape
    query = np.eye(gh * gw, dtype=np.float32).reshape(gh, gw, gh * gw)
    cand = query.reshape(gh * gw, -1)[best.ravel()].reshape(gh, gw, -1)
    return query, cand


def test_scores_rank_a_clean_match_above_noise():
    rng = np.random.default_rng(5)
    q = _unique_grid(6, 6, d=16, seed=1)
    noisy = q + 0.1 * rng.standard_normal(q.shape).astype(np.float32)
    unrelated = rng.standard_normal((3, 6, 6, 16)).astype(np.float32)
    r = spatial_scores(q, np.concatenate([unrelated, noisy[None]]))
    assert int(np.argmax(r.scores)) == 3
    assert r.scores[3] == pytest.approx(1.0)
    assert (r.scores[:3] < 0.6).all()


def test_empty_candidates_and_shape_mismatch():
    q = _unique_grid(3, 3)
    r = spatial_scores(q, np.empty((0, 3, 3, 8), np.float32))
    assert r.scores.shape == (0,) and r.raw.shape == (0,) and r.shifts.shape == (0, 2)
    with pytest.raises(ValueError, match="do not match"):
        spatial_scores(q, np.zeros((2, 3, 4, 8), np.float32))
    with pytest.raises(ValueError, match="do not match"):
        spatial_scores(q, np.zeros((3, 3, 8), np.float32))


@pytest.mark.parametrize("gh, gw", [(1, 1), (2, 3), (13, 13), (4, 7)])
def test_max_raw_score_is_the_literal_identity_score(gh, gw):
    q = _unique_grid(gh, gw, d=4, seed=gh * 10 + gw)
    if gh * gw <= 30:
        assert spatial_score_literal(q, q) == max_raw_score(gh, gw)
    assert spatial_scores(q, q[None]).raw[0] == max_raw_score(gh, gw)


def test_float16_widening_is_numpys_for_every_bit_pattern():
    """The torch conversion must give numpy's float32 for all 65,536 float16 values, compared as
    bits: subnormals, signed zeros and infinities included. NaNs stay NaN (torch quiets a
    signalling NaN's payload; stored codes are finite, the database refuses others)."""
    every = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16).view(np.float16).reshape(256, 16, 16)
    widened = as_float32(every)
    assert widened.dtype == np.float32 and widened.shape == every.shape
    nan = np.isnan(every)
    assert np.isnan(widened[nan]).all() and nan.sum() == 2 * 1023
    np.testing.assert_array_equal(widened[~nan].view(np.uint32), every[~nan].astype(np.float32).view(np.uint32))
    strided = every[:, ::3]  # a gathered, non-contiguous view converts too
    np.testing.assert_array_equal(as_float32(strided), strided.astype(np.float32))


def test_float16_widening_takes_read_only_arrays_without_warning():
    """A memory-mapped map's grids are read-only; torch.from_numpy would warn on them."""
    stored = np.linspace(-3, 3, 13 * 13 * 8, dtype=np.float32).astype(np.float16).reshape(1, 13, 13, 8)
    stored.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        widened = as_float32(stored)
    np.testing.assert_array_equal(widened, stored.astype(np.float32))
    assert not stored.flags.writeable


def test_float16_widening_stays_below_atens_parallel_grain():
    """Each torch copy must stay at or below ATen's grain (32,768 elements), so it runs in the
    calling thread: a parallel copy woke torch's OpenMP pool, whose spinning threads slowed the
    BLAS product after it about threefold (and would take the backbone's cores in a SLAM run)."""
    assert 0 < spatial._SERIAL_COPY <= 32768


def test_float16_storage_scores_as_its_float32_values():
    rng = np.random.default_rng(7)
    query = rng.standard_normal((13, 13, 24), dtype=np.float32)
    stored = rng.standard_normal((9, 13, 13, 24), dtype=np.float32).astype(np.float16)
    half, full = spatial_scores(query, stored, chunk=4), spatial_scores(query, stored.astype(np.float32), chunk=4)
    np.testing.assert_array_equal(half.raw, full.raw)
    np.testing.assert_array_equal(half.shifts, full.shifts)


@given(grids())
@settings(max_examples=80, deadline=None)
def test_the_torch_batch_equals_the_literal_algorithm(grid):
    """Stage II on a torch device (run here on the CPU): small integer codes make every distance
    exact, so it must give the paper's loop's scores and numpy's shifts exactly."""
    query, cands = grid
    result = spatial_scores_torch(query, cands, "cpu")
    np.testing.assert_array_equal(result.raw, [spatial_score_literal(query, cand) for cand in cands])
    reference = spatial_scores(query, cands)
    np.testing.assert_array_equal(result.scores, reference.scores)
    np.testing.assert_array_equal(result.shifts, reference.shifts)


def test_several_queries_in_one_torch_batch_score_as_each_alone():
    """A sequence step's terms of several earlier queries go to the device together; each group
    must get exactly the scores its own call gives (float codes, float16 storage, empty groups)."""
    rng = np.random.default_rng(5)
    groups = []
    for n in (4, 0, 7, 1):
        query = rng.normal(size=(13, 13, 16)).astype(np.float32)
        stored = rng.normal(size=(n, 13, 13, 16)).astype(np.float16)
        if n:
            stored[0] = query.astype(np.float16)  # the place itself
        groups.append((query, stored))
    together = spatial_scores_torch_many(groups, "cpu")
    assert [len(scores) for scores in together] == [4, 0, 7, 1]
    for (query, stored), scores in zip(groups, together, strict=True):
        np.testing.assert_array_equal(scores, spatial_scores_torch(query, stored, "cpu").scores)
        np.testing.assert_array_equal(scores, spatial_scores(query, stored).scores)
    assert all(scores[0] == 1.0 for scores in together if len(scores))
    assert spatial_scores_torch_many([], "cpu") == []
    assert [len(s) for s in spatial_scores_torch_many([groups[1], groups[1]], "cpu")] == [0, 0]
    with pytest.raises(ValueError, match="do not match"):
        spatial_scores_torch_many([groups[0], (groups[2][0], groups[2][1][:, :12])], "cpu")


def test_the_torch_batch_takes_float16_storage_and_no_candidates():
    rng = np.random.default_rng(3)
    query = rng.normal(size=(13, 13, 16)).astype(np.float32)
    stored = rng.normal(size=(5, 13, 13, 16)).astype(np.float16)
    stored[2] = query.astype(np.float16)  # the place itself: every cell keeps its place
    result = spatial_scores_torch(query, stored, "cpu")
    assert result.scores[2] == 1.0 and tuple(result.shifts[2]) == (0, 0)
    np.testing.assert_array_equal(result.raw, spatial_scores(query, stored).raw)
    empty = spatial_scores_torch(query, stored[:0], "cpu")
    assert empty.scores.shape == (0,) and empty.shifts.shape == (0, 2)
    with pytest.raises(ValueError, match="do not match"):
        spatial_scores_torch(query, stored[:, :12], "cpu")


def test_stage_two_runs_where_the_settings_say():
    import torch

    from loopclosure.config import VPRConfig
    from loopclosure.errors import LoopClosureInputError
    from loopclosure.spatial_torch import _device

    assert _device("cpu", "cuda") == "cpu"
    assert _device("auto", "cpu") == "cpu"  # the backbone on the CPU: numpy, whatever the machine has
    assert _device("auto", "auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(LoopClosureInputError, match="vpr.spatial.device: cuda"):
            _device("cuda", "auto")
    rng = np.random.default_rng(0)
    query = rng.normal(size=(4, 4, 8)).astype(np.float32)
    cands = rng.normal(size=(3, 4, 4, 8)).astype(np.float32)
    config = VPRConfig.model_validate({"spatial": {"device": "cpu"}})
    np.testing.assert_array_equal(stage2_scores(query, cands, config).raw, spatial_scores(query, cands).raw)
