"""Shared fixtures: where the real benchmarks and weights live."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

# tests import their shared helpers (cli_helpers) by module name; importlib mode adds no path
sys.path.insert(0, str(Path(__file__).resolve().parent))

SHARED = Path(os.environ.get("SSMVPR_SHARED", Path(__file__).resolve().parents[2] / "shared"))


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.fail(f"shared data folder not found at {SHARED}; set SSMVPR_SHARED")
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
