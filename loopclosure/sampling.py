"""Choosing a subset that covers a sequence: the images PCA is fitted on and the images an int8
backbone is calibrated on are spread over the whole route, never its first stretch."""

from __future__ import annotations

import numpy as np


def evenly_spaced(n: int, k: int) -> np.ndarray:
    """k indices spread over range(n) (all of them when k >= n): a fit set that covers the route."""
    if k >= n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, k).round().astype(np.int64))
