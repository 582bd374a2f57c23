"""Shared fixtures: where the real benchmarks and weights live."""

from __future__ import annotations

import hashlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

# tests import their shared helpers (cli_helpers) by module name; importlib mode adds no path
sys.path.insert(0, str(Path(__file__).resolve().parent))

SHARED = Path(os.environ.get("SSMVPR_SHARED", Path(__file__).resolve().parents[2] / "shared"))


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The real benchmarks and weights (`../shared`, or $SSMVPR_SHARED). Without them the tests
    that read them are skipped, saying why; where they must be there (CI exports
    SSMVPR_REQUIRE_SHARED=1), their absence fails instead of skipping."""
    if not SHARED.is_dir():
        message = f"shared data folder not found at {SHARED} (set SSMVPR_SHARED to where it is)"
        if os.environ.get("SSMVPR_REQUIRE_SHARED") == "1":
            pytest.fail(message)
        pytest.skip(message)
    return SHARED


@pytest.fixture(scope="session")
def weights_path(shared_dir: Path) -> Path:
    return shared_dir / "weights" / "vgg16_imagenet_conv.pth"


@pytest.fixture(scope="session")
def corridor_dir(shared_dir: Path) -> Path:
    return shared_dir / "data" / "corridor"


@pytest.fixture(scope="session")
def gardens_dir(shared_dir: Path) -> Path:
    return shared_dir / "data" / "gardens_point_mini"


class BackbonePasses:
    """The real fp32 backbone's maps of every image it has seen this session, per image: Corridor
    is encoded by three test modules (stage-I index, `loop-eval`, `vpr-eval`) through their own
    backbones, in batches of their own. Reduced precisions and int8 are never remembered (their
    tests are about those passes), nor random weights unless `random_weights` (a module whose
    tests draw them from one seed): the key holds the weights' digest, so other weights never
    get these maps."""

    def __init__(self, random_weights: bool = False) -> None:
        self.maps: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
        self.passes = 0  # images the backbone actually ran on
        self.random_weights = random_weights

    def _weights_key(self, backbone: Any) -> bytes | None:
        if (backbone.config.weights == "random" and not self.random_weights) or backbone.precision != "fp32":
            return None
        if backbone._int8 is not None or backbone._calibrating is not None:
            return None
        key = backbone.__dict__.get("_test_weights_key")
        if key is None:
            digest = hashlib.sha1(repr(sorted(backbone.config.model_dump().items())).encode())
            for parameter in backbone.net.parameters():
                digest.update(parameter.detach().cpu().float().numpy().tobytes())
            key = backbone.__dict__["_test_weights_key"] = digest.digest()
        return key

    def call(self, original: Any, backbone: Any, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        weights = self._weights_key(backbone)
        if weights is None or images.ndim != 4:
            return original(backbone, images)
        keys = [weights + hashlib.sha1(np.ascontiguousarray(image).tobytes()).digest() for image in images]
        first: dict[bytes, int] = {}
        for i, key in enumerate(keys):
            first.setdefault(key, i)
        todo = [i for key, i in first.items() if key not in self.maps]
        if todo:
            stage1, stage2 = original(backbone, images[todo])
            self.passes += len(todo)
            for j, i in enumerate(todo):
                self.maps[keys[i]] = (stage1[j].copy(), stage2[j].copy())
        return (np.stack([self.maps[key][0] for key in keys]), np.stack([self.maps[key][1] for key in keys]))


@pytest.fixture(scope="session")
def backbone_passes() -> BackbonePasses:
    return BackbonePasses()


def _remembering(passes: BackbonePasses) -> Iterator[BackbonePasses]:
    from loopclosure.backbone import Backbone

    original = Backbone.__call__
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Backbone, "__call__", lambda self, images: passes.call(original, self, images))
        yield passes


@pytest.fixture(scope="module")
def shared_backbone_passes(backbone_passes: BackbonePasses) -> Iterator[BackbonePasses]:
    """For a module: the real backbone runs once per distinct image over the session's modules
    that ask for this (see BackbonePasses)."""
    yield from _remembering(backbone_passes)


@pytest.fixture(scope="module")
def seeded_random_backbone_passes() -> Iterator[BackbonePasses]:
    """For a module whose tests run the same images through random weights drawn from the same
    seed (torch.manual_seed before each backbone is made): within the module the backbone runs
    once per distinct image and weights."""
    yield from _remembering(BackbonePasses(random_weights=True))
