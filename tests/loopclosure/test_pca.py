"""loopclosure.pca: fitting, projection, whitening and the codebook file."""

from __future__ import annotations

import numpy as np
import pytest

from loopclosure.config import PCAConfig
from loopclosure.errors import LoopClosureInputError
from loopclosure.pca import Codebooks, PCAProjection, fit_pca


def _low_rank(n: int, dim_in: int, rank: int, seed: int = 0, noise: float = 0.0):
    rng = np.random.default_rng(seed)
    basis = np.linalg.qr(rng.standard_normal((dim_in, rank)))[0].T  # (rank, D) orthonormal rows
    scales = np.linspace(5.0, 1.0, rank)
    z = rng.standard_normal((n, rank)) * scales
    offset = rng.standard_normal(dim_in) * 3.0
    x = z @ basis + offset + noise * rng.standard_normal((n, dim_in))
    return x.astype(np.float32), basis, offset


def test_fit_recovers_a_low_rank_subspace():
    x, basis, offset = _low_rank(n=300, dim_in=60, rank=6)
    pca = fit_pca(x, PCAConfig(dim=6, l2_normalize_output=False))
    assert pca.components.shape == (6, 60) and pca.mean.shape == (60,)
    assert pca.input_dim == 60 and pca.dim == 6
    # the component rows span the generating subspace
    overlap = np.linalg.svd(pca.components @ basis.T, compute_uv=False)
    np.testing.assert_allclose(overlap, 1.0, atol=1e-4)
    # projection then back-projection reconstructs the data
    y = pca.transform(x)
    assert y.dtype == np.float32 and y.shape == (300, 6)
    recon = y @ pca.components + pca.mean
    rel = np.linalg.norm(recon - x) / np.linalg.norm(x - x.mean(0))
    assert rel < 1e-4
    np.testing.assert_allclose(pca.mean, x.mean(0), rtol=1e-4, atol=1e-4)
    # components are orthonormal and variances ordered
    np.testing.assert_allclose(pca.components @ pca.components.T, np.eye(6), atol=1e-5)
    assert (np.diff(pca.explained_variance) <= 0).all()


def test_randomized_solver_path_also_recovers_subspace():
    """dim well below 0.8 * min(n, D) takes the randomized solver."""
    x, basis, _ = _low_rank(n=400, dim_in=200, rank=10, seed=1, noise=1e-3)
    pca = fit_pca(x, PCAConfig(dim=10, l2_normalize_output=False))
    overlap = np.linalg.svd(pca.components @ basis.T, compute_uv=False)
    assert overlap.min() > 0.999


def test_transform_keeps_leading_axes_and_l2_normalises():
    x, _, _ = _low_rank(n=120, dim_in=30, rank=8, seed=2)
    pca = fit_pca(x, PCAConfig(dim=8))  # l2_normalize_output defaults to True
    grid = x[:24].reshape(2, 3, 4, 30)
    y = pca.transform(grid)
    assert y.shape == (2, 3, 4, 8)
    np.testing.assert_allclose(np.linalg.norm(y, axis=-1), 1.0, rtol=1e-5)
    raw = (x[:24] - pca.mean) @ pca.components.T
    np.testing.assert_allclose(y.reshape(24, 8), raw / np.linalg.norm(raw, axis=1, keepdims=True), rtol=1e-4, atol=1e-5)
    with pytest.raises(LoopClosureInputError, match="30 dims, got 29"):
        pca.transform(x[:, :29])


def test_whitening_gives_unit_variance_per_component():
    x, _, _ = _low_rank(n=500, dim_in=40, rank=40, seed=3)
    plain = fit_pca(x, PCAConfig(dim=5, l2_normalize_output=False))
    white = fit_pca(x, PCAConfig(dim=5, whiten=True, l2_normalize_output=False))
    y_plain, y_white = plain.transform(x), white.transform(x)
    assert np.var(y_plain, axis=0, ddof=1)[0] > 10  # the leading variance is ~25 unwhitened
    np.testing.assert_allclose(np.var(y_white, axis=0, ddof=1), 1.0, rtol=1e-3)
    np.testing.assert_allclose(
        np.abs(y_white * np.sqrt(white.explained_variance)), np.abs(y_plain), rtol=1e-3, atol=1e-3
    )


def test_fewer_samples_than_dim_is_a_clear_error():
    x = np.random.default_rng(0).standard_normal((50, 300)).astype(np.float32)
    with pytest.raises(LoopClosureInputError, match=r"stage-I PCA: 50 samples of 300 dims cannot give 100"):
        fit_pca(x, PCAConfig(dim=100), name="stage-I PCA")
    with pytest.raises(LoopClosureInputError, match="cannot give 100"):
        fit_pca(x[:, :40].copy(), PCAConfig(dim=100))  # fewer dimensions than components


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_samples_are_refused(bad):
    x = np.random.default_rng(0).standard_normal((40, 10)).astype(np.float32)
    x[7, 3] = bad
    with pytest.raises(LoopClosureInputError, match="NaN or inf"):
        fit_pca(x, PCAConfig(dim=4))


def test_non_2d_samples_are_refused():
    with pytest.raises(LoopClosureInputError, match=r"\(n, D\)"):
        fit_pca(np.zeros((4, 5, 6), np.float32), PCAConfig(dim=2))


def test_subsampling_is_seeded():
    x = np.random.default_rng(4).standard_normal((600, 30)).astype(np.float32)
    cfg = PCAConfig(dim=5, max_fit_samples=100, seed=7)
    a, b = fit_pca(x, cfg), fit_pca(x, cfg)
    np.testing.assert_array_equal(a.components, b.components)
    np.testing.assert_array_equal(a.mean, b.mean)
    c = fit_pca(x, PCAConfig(dim=5, max_fit_samples=100, seed=8))
    assert not np.array_equal(a.mean, c.mean)  # another subset of the 600
    full = fit_pca(x, PCAConfig(dim=5))
    assert not np.array_equal(a.mean, full.mean)
    # the subset is drawn from the rows: its mean is the mean of 100 of them
    np.testing.assert_allclose(full.mean, x.mean(0), rtol=1e-4, atol=1e-5)


def _codebooks(seed: int = 0) -> Codebooks:
    rng = np.random.default_rng(seed)
    s1 = fit_pca(rng.standard_normal((60, 20)).astype(np.float32), PCAConfig(dim=6, whiten=True))
    s2 = fit_pca(rng.standard_normal((80, 12)).astype(np.float32), PCAConfig(dim=4, l2_normalize_output=False))
    return Codebooks(s1, s2)


def test_codebooks_round_trip_bit_identical(tmp_path):
    books = _codebooks()
    path = tmp_path / "sub" / "codebooks.npz"
    books.save(path)
    loaded = Codebooks.load(path)
    for a, b in ((books.stage1, loaded.stage1), (books.stage2, loaded.stage2)):
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.components, b.components)
        np.testing.assert_array_equal(a.explained_variance, b.explained_variance)
        assert (a.whiten, a.l2_normalize_output) == (b.whiten, b.l2_normalize_output)
    assert loaded.stage1.whiten and loaded.stage1.l2_normalize_output
    assert not loaded.stage2.whiten and not loaded.stage2.l2_normalize_output
    x = np.random.default_rng(9).standard_normal((5, 20)).astype(np.float32)
    np.testing.assert_array_equal(books.stage1.transform(x), loaded.stage1.transform(x))
    x2 = np.random.default_rng(9).standard_normal((5, 12)).astype(np.float32)
    np.testing.assert_array_equal(books.stage2.transform(x2), loaded.stage2.transform(x2))
    assert not list(path.parent.glob("*.tmp"))  # the atomic write left no temporary behind


def test_loading_something_else_is_an_input_error(tmp_path):
    other = tmp_path / "other.npz"
    np.savez(other, weights=np.zeros(3))
    with pytest.raises(LoopClosureInputError, match="not a PCA codebook file.*other.npz"):
        Codebooks.load(other)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"this is not a zip file at all")
    with pytest.raises(LoopClosureInputError, match="garbage.npz"):
        Codebooks.load(garbage)
    with pytest.raises(LoopClosureInputError, match="not found.*missing.npz"):
        Codebooks.load(tmp_path / "missing.npz")
    half = tmp_path / "half.npz"
    np.savez(half, **_codebooks().stage1.to_arrays("stage1_"))  # no stage-II arrays
    with pytest.raises(LoopClosureInputError, match="half.npz"):
        Codebooks.load(half)


def test_projection_from_arrays_round_trip():
    p = PCAProjection(
        mean=np.arange(4, dtype=np.float32),
        components=np.eye(2, 4, dtype=np.float32),
        explained_variance=np.array([4.0, 1.0], np.float32),
        whiten=True,
        l2_normalize_output=False,
    )
    q = PCAProjection.from_arrays(p.to_arrays("x_"), "x_")
    y = q.transform(np.array([[2.0, 5.0, 9.0, 9.0]], np.float32))
    np.testing.assert_allclose(y, [[(2.0 - 0.0) / 2.0, (5.0 - 1.0) / 1.0]])


def test_subsample_smaller_than_dim_is_a_clear_error():
    x = np.random.default_rng(0).standard_normal((300, 50)).astype(np.float32)
    with pytest.raises(LoopClosureInputError, match="max_fit_samples|samples"):
        fit_pca(x, PCAConfig(dim=20, max_fit_samples=10))
