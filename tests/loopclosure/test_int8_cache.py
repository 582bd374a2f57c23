"""The int8 model cache keeps the most recently used models (`int8_runtime.prune_cache`)."""

from __future__ import annotations

import os
from pathlib import Path

from loopclosure.int8_runtime import _mark_used, prune_cache


def _model(folder: Path, name: str, used_at: float) -> Path:
    path = folder / f"vgg16_int8_{name}.onnx"
    path.write_bytes(b"model")
    os.utime(path, (used_at, used_at))
    return path


def test_the_least_recently_used_models_go_and_nothing_else(tmp_path):
    old, middle, new = (_model(tmp_path, name, t) for name, t in (("a", 1.0e9), ("b", 1.2e9), ("c", 1.4e9)))
    other = tmp_path / "notes.txt"
    other.write_text("not a model")
    assert prune_cache(tmp_path, keep=2) == [old]
    assert middle.exists() and new.exists() and other.exists()
    assert prune_cache(tmp_path, keep=2) == []


def test_a_cache_hit_becomes_the_most_recently_used(tmp_path):
    old, new = _model(tmp_path, "a", 1.0e9), _model(tmp_path, "b", 1.2e9)  # both before now
    _mark_used(old)  # what a cache hit does
    assert prune_cache(tmp_path, keep=1) == [new]
    assert old.exists()


def test_an_empty_or_missing_cache_prunes_nothing(tmp_path):
    assert prune_cache(tmp_path, keep=0) == []
    assert prune_cache(tmp_path / "absent", keep=0) == []
