"""Freed heap pages go back to the OS every few keyframes (see ssmvpr_slam/app/heap.py for why)."""

from __future__ import annotations

import platform

import pytest

from ssmvpr_slam.app import heap


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="malloc_trim is glibc's")
def test_glibc_trims() -> None:
    assert heap.release_free_heap() is True


def test_the_trimmer_runs_once_per_interval_of_keyframes(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[int] = []
    monkeypatch.setattr(heap, "release_free_heap", lambda: calls.append(1) or True)
    trimmer = heap.HeapTrimmer(every=25)
    for keyframes in [0, 1, 1, 24, 25, 25, 26, 49, 50, 80, 80, 105]:  # a step may add no keyframe
        trimmer.after(keyframes)
    assert len(calls) == trimmer.calls == 4  # at 25, 50, 80 (>= 75) and 105
    assert trimmer.seconds >= 0.0


def test_zero_never_trims(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(heap, "release_free_heap", lambda: pytest.fail("trimmed"))
    trimmer = heap.HeapTrimmer(every=0)
    for keyframes in range(200):
        trimmer.after(keyframes)
    assert trimmer.calls == 0


def test_without_a_c_library_it_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(heap, "_malloc_trim", lambda: None)
    assert heap.release_free_heap() is False
