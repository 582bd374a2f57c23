"""Checks on the named arrays a checkpoint saved for the detector and its parts.

A state that loads without an error but resumes wrongly (NaN scores, places outside the map)
is worse than a refused one, so each part checks its own arrays before anything changes.
"""

from __future__ import annotations

import numpy as np

from loopclosure.errors import LoopClosureInputError


def saved_ints(arrays: dict[str, np.ndarray], name: str, lo: int, hi: int) -> np.ndarray:
    """`arrays[name]` as whole numbers in lo .. hi - 1, or LoopClosureInputError naming it."""
    value = np.asarray(arrays[name])
    if value.dtype.kind not in "iu" or (value.size and (value.min() < lo or value.max() >= hi)):
        raise LoopClosureInputError(f"detector state {name}: expected integers in {lo}..{hi - 1}, got {value!r:.80}")
    return value


def saved_finite(arrays: dict[str, np.ndarray], name: str) -> np.ndarray:
    """`arrays[name]` as finite numbers, or LoopClosureInputError naming it."""
    value = np.asarray(arrays[name])
    if value.dtype.kind not in "fiu" or not np.isfinite(value).all():
        raise LoopClosureInputError(f"detector state {name}: expected finite numbers, got {value!r:.80}")
    return value
