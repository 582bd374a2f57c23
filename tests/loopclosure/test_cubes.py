"""loopclosure.cubes.extract_cubes against hand-sliced windows."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from loopclosure.config import CubeConfig, grid_side
from loopclosure.cubes import extract_cubes


def _manual_cube(maps: np.ndarray, b: int, gi: int, gj: int, size: int, stride: int, normalise: bool) -> np.ndarray:
    window = maps[b, :, gi * stride : gi * stride + size, gj * stride : gj * stride + size].astype(np.float64)
    if normalise:
        norms = np.sqrt((window**2).sum(axis=0, keepdims=True))  # one norm per (row, col) location
        window = window / norms
    return window.reshape(-1)  # C-major, then row, then column: (C, L, L) order


@pytest.mark.parametrize(
    "side, cube, stride, grid, dim",
    [(14, 7, 2, 4, 512 * 49), (28, 3, 2, 13, 512 * 9)],
)
def test_paper_grid_shapes(side, cube, stride, grid, dim):
    maps = np.random.default_rng(0).standard_normal((2, 512, side, side), dtype=np.float32)
    cubes = extract_cubes(maps, CubeConfig(cube_size=cube, stride=stride))
    assert cubes.shape == (2, grid, grid, dim)
    assert cubes.dtype == np.float32
    assert grid == grid_side(side, CubeConfig(cube_size=cube, stride=stride))


@pytest.mark.parametrize("normalise", [True, False])
def test_every_cube_equals_the_hand_sliced_window(normalise):
    rng = np.random.default_rng(1)
    maps = rng.standard_normal((2, 5, 10, 9)).astype(np.float32)
    size, stride = 3, 2
    cubes = extract_cubes(maps, CubeConfig(cube_size=size, stride=stride, l2_normalize_locations=normalise))
    gh, gw = (10 - size) // stride + 1, (9 - size) // stride + 1  # 4, 4: the last row/col is dropped
    assert cubes.shape == (2, gh, gw, 5 * size * size)
    for b in range(2):
        for gi in range(gh):
            for gj in range(gw):
                np.testing.assert_allclose(
                    cubes[b, gi, gj], _manual_cube(maps, b, gi, gj, size, stride, normalise), rtol=1e-5, atol=1e-6
                )


def test_channel_major_flattening_is_distinguishable():
    """Values encode (c, y, x) so any other flattening order would show."""
    c, h, w = 3, 4, 4
    maps = np.zeros((1, c, h, w), np.float32)
    for ci in range(c):
        for y in range(h):
            for x in range(w):
                maps[0, ci, y, x] = 100 * ci + 10 * y + x
    cube = extract_cubes(maps, CubeConfig(cube_size=2, stride=2, l2_normalize_locations=False))
    assert cube.shape == (1, 2, 2, 12)
    # cell (1, 0) covers rows 2..3, cols 0..1
    expected = [100 * ci + 10 * y + x for ci in range(c) for y in (2, 3) for x in (0, 1)]
    np.testing.assert_array_equal(cube[0, 1, 0], expected)


@given(
    seed=st.integers(0, 2**31 - 1),
    c=st.integers(1, 8),
    h=st.integers(1, 7),
    w=st.integers(1, 7),
)
@settings(max_examples=40, deadline=None)
def test_size_one_cubes_are_unit_length_locations(seed, c, h, w):
    maps = np.random.default_rng(seed).standard_normal((2, c, h, w)).astype(np.float32) * 50
    cubes = extract_cubes(maps, CubeConfig(cube_size=1, stride=1))
    assert cubes.shape == (2, h, w, c)
    np.testing.assert_allclose(np.linalg.norm(cubes, axis=-1), 1.0, rtol=1e-5)
    # direction unchanged: the cube is the location's vector divided by its norm
    locations = maps.transpose(0, 2, 3, 1)
    np.testing.assert_allclose(
        cubes * np.linalg.norm(locations, axis=-1, keepdims=True), locations, rtol=1e-4, atol=1e-4
    )


def test_normalisation_makes_each_location_of_a_cube_unit_length():
    maps = np.random.default_rng(2).standard_normal((1, 6, 7, 7)).astype(np.float32) * 30
    cubes = extract_cubes(maps, CubeConfig(cube_size=3, stride=2))
    per_location = cubes.reshape(1, 3, 3, 6, 3, 3)  # (B, gh, gw, C, L, L)
    np.testing.assert_allclose(np.linalg.norm(per_location, axis=3), 1.0, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(cubes, axis=-1), 3.0, rtol=1e-5)  # sqrt(L*L) unit locations


def test_all_zero_location_stays_zero_not_nan():
    maps = np.random.default_rng(3).standard_normal((1, 4, 3, 3)).astype(np.float32)
    maps[0, :, 1, 1] = 0.0
    cubes = extract_cubes(maps, CubeConfig(cube_size=1, stride=1))
    assert np.isfinite(cubes).all()
    np.testing.assert_array_equal(cubes[0, 1, 1], 0.0)


def test_input_is_not_modified_and_float64_is_accepted():
    maps = np.random.default_rng(4).standard_normal((1, 4, 5, 5))
    before = maps.copy()
    cubes = extract_cubes(maps, CubeConfig(cube_size=3, stride=1))
    np.testing.assert_array_equal(maps, before)
    assert cubes.dtype == np.float32 and cubes.shape == (1, 3, 3, 36)


def test_non_4d_maps_are_refused():
    with pytest.raises(ValueError, match="B, C, H, W"):
        extract_cubes(np.zeros((4, 5, 5), np.float32), CubeConfig(cube_size=1, stride=1))
