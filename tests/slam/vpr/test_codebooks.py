"""`fit-pca`'s work (`ssmvpr_slam.vpr.codebooks`): the images it fits on are spread over the whole
folder, and the codebooks it writes load back with the configured dimensions (random weights
on small synthetic images: the mechanics, not recognition)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from cli_helpers import clean_ssmvpr_environment  # noqa: F401
from rich.console import Console

from loopclosure.config import VPRConfig
from loopclosure.errors import LoopClosureInputError
from loopclosure.pca import Codebooks
from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.vpr.codebooks import fit_codebooks, fit_images


def _folder(path: Path, n: int) -> Path:
    path.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        assert cv2.imwrite(str(path / f"{i:03d}.png"), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    return path


def _small(spatial: dict[str, Any]) -> VPRConfig:
    """Random weights on 64 px inputs: one stage-I cube per image, 4 components."""
    return load_config(
        overrides={"vpr": {"backbone": {"weights": "random", "device": "cpu", "input_size": 64},
                           "filtering": {"cubes": {"cube_size": 4, "stride": 2}, "pca": {"dim": 4}}, "spatial": spatial}}
    ).vpr  # fmt: skip


def test_the_fit_images_cover_the_folder(tmp_path: Path) -> None:
    folder = _folder(tmp_path / "images", 10)
    files = sorted(folder.iterdir())
    chosen = fit_images(folder, 4)
    assert len(chosen) == 4 and chosen == sorted(chosen) and chosen[0] == files[0] and chosen[-1] == files[-1]
    assert fit_images(folder, 30) == files  # a folder smaller than the limit: all of it
    with pytest.raises(LoopClosureInputError, match="no images"):
        fit_images(_folder(tmp_path / "empty", 0), 4)


def test_the_codebooks_are_fitted_written_and_load_back(tmp_path: Path) -> None:
    config = _small({"cubes": {"cube_size": 2, "stride": 1}, "pca": {"dim": 6, "max_fit_images": 5}})
    output = tmp_path / "codebooks.npz"
    codebooks = fit_codebooks(_folder(tmp_path / "images", 8), output, config, Console(file=io.StringIO()))
    assert (codebooks.stage1.dim, codebooks.stage2.dim) == (4, 6)
    loaded = Codebooks.load(output)
    assert (loaded.stage1.dim, loaded.stage2.dim) == (4, 6)
    np.testing.assert_array_equal(loaded.stage2.components, codebooks.stage2.components)


def test_the_fit_uses_no_more_images_than_configured(tmp_path: Path) -> None:
    """Three images of eight give three stage-I vectors (one cube each at 64 px): too few for
    four components, and said so; nothing is written."""
    config = _small({"pca": {"max_fit_images": 3}})
    output = tmp_path / "codebooks.npz"
    with pytest.raises(LoopClosureInputError, match="stage-I PCA: 3 samples"):
        fit_codebooks(_folder(tmp_path / "images", 8), output, config, Console(file=io.StringIO()))
    assert not output.exists()
