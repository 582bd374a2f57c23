"""The one-import API: `loopclosure` and `ssmvpr_slam` export what a user needs, lazily, and
`PlaceRecognizer` wires backbone, PCA, database and recogniser (random weights here; the
README's example runs it on real images with the real weights, tests/test_readme.py)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import loopclosure
import ssmvpr_slam
from loopclosure import LoopDetector, LoopProposal, PlaceRecognizer, Recognition, VPRConfig
from loopclosure.errors import LoopClosureInputError


def test_every_export_resolves_and_none_is_left_out() -> None:
    for package in (loopclosure, ssmvpr_slam):
        assert package.__all__ == sorted(package._EXPORTS)
        for name in package.__all__:
            assert getattr(package, name).__name__ == name
        with pytest.raises(AttributeError, match="no attribute 'nope'"):
            package.nope  # noqa: B018


def test_importing_the_packages_loads_no_torch() -> None:
    code = "import sys, loopclosure, ssmvpr_slam; print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "False"


def _images(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (120, 160, 3), dtype=np.uint8) for _ in range(n)]


@pytest.fixture(scope="module")
def recognizer() -> PlaceRecognizer:
    recognizer = PlaceRecognizer.from_config(weights="random", device="cpu")
    assert len(recognizer) == 0
    with pytest.raises(LoopClosureInputError, match="add reference images first"):
        recognizer.query(_images(1)[0])
    assert recognizer.add_references(_images(8)) == list(range(8))
    return recognizer


def test_a_reference_is_recognised_as_itself(recognizer: PlaceRecognizer) -> None:
    references = _images(8)
    found = recognizer.query(references[5])
    assert isinstance(found, Recognition) and found.best_place == 5
    assert repr(found).startswith("Recognition(best_place=5, best_score=") and "array" not in repr(found)


def test_later_references_reuse_the_fitted_codebooks(recognizer: PlaceRecognizer) -> None:
    codebooks = recognizer.encoder.codebooks
    assert recognizer.add_references(_images(2, seed=1)) == [8, 9]
    assert recognizer.encoder.codebooks is codebooks and len(recognizer) == 10
    assert recognizer.query(_images(2, seed=1)[1]).best_place == 9
    with pytest.raises(LoopClosureInputError, match="no images"):
        recognizer.add_references([])


def test_from_config_leaves_the_callers_config_alone() -> None:
    config = VPRConfig()
    detector = LoopDetector.from_config(config, weights="random", device="cpu")
    assert config.backbone.weights is None and detector.vpr.backbone.weights == "random"
    assert detector.process(_images(1)[0], 0) is None  # the PCA warm-up
    assert LoopProposal.__name__ == "LoopProposal"
