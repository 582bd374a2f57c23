"""Giving freed heap pages back to the operating system during a long run.

A long run's process grew several times faster than what the run keeps, with no leak in any
part (docs/benchmarks.md, "Memory per keyframe in a long run"): the rest was free memory that
glibc's allocator held on to. A frame's transient arrays (a raw scan, images, feature
maps) are allocated from the heap once glibc's dynamic mmap threshold has risen, and the small
objects a keyframe keeps for the whole run land between them, so the freed space cannot shrink
the heap. `malloc_trim(0)` hands every free page back (madvise), wherever it lies; calling it
every few keyframes kept the growth to what the run holds. Elsewhere than glibc it is a no-op.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import time
from collections.abc import Callable
from functools import cache


@cache
def _malloc_trim() -> Callable[[int], int] | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        return ctypes.CDLL(name).malloc_trim  # glibc only
    except (OSError, AttributeError):
        return None


def release_free_heap() -> bool:
    """Return the allocator's free pages to the OS; False where the C library cannot."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


class HeapTrimmer:
    """Calls `release_free_heap` once every `every` keyframes (0: never), and keeps its cost."""

    def __init__(self, every: int) -> None:
        self.every = every
        self.calls = 0
        self.seconds = 0.0
        self._next = every

    def after(self, keyframes: int) -> None:
        """Trim if `keyframes` reached the next multiple since the last trim."""
        if self.every <= 0 or keyframes < self._next:
            return
        start = time.perf_counter()
        if release_free_heap():
            self.calls += 1
        self.seconds += time.perf_counter() - start
        self._next = keyframes + self.every
