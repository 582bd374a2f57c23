"""Deterministic hashing and smooth noise: the simulator's only source of procedural variety.

Everything the world looks like is a pure function of (seed, channel, integer keys), so a
frame can be regenerated alone and two visits of a place see the same thing unless a
channel says otherwise (a visit index, a time epoch).
"""

from __future__ import annotations

import numpy as np

_HASH_MULTIPLIERS = tuple(
    np.uint32(m) for m in (0x27D4EB2F, 0x165667B1, 0xC2B2AE3D, 0x9E3779B1, 0x61C88647, 0x7FEB352D, 0x846CA68B)
)


def _mix32(x: np.ndarray) -> np.ndarray:
    """Avalanche a uint32 array (xor-shift-multiply finaliser; wraps modulo 2**32)."""
    with np.errstate(over="ignore"):
        x = x ^ (x >> np.uint32(16))
        x = x * np.uint32(0x7FEB352D)
        x = x ^ (x >> np.uint32(15))
        x = x * np.uint32(0x846CA68B)
        return x ^ (x >> np.uint32(16))


def hash_u32(*keys) -> np.ndarray:
    """Deterministic uint32 hash of integer arrays (broadcast), order-sensitive.

    Keys are combined with distinct odd multipliers (wrapping) and then avalanched twice;
    floats are floored first.
    """
    if len(keys) > len(_HASH_MULTIPLIERS):
        raise ValueError(f"hash_u32 takes at most {len(_HASH_MULTIPLIERS)} keys")
    h = np.uint32(0x9E3779B9)
    with np.errstate(over="ignore"):
        for mult, k in zip(_HASH_MULTIPLIERS, keys):
            k = np.asarray(k)
            if k.dtype.kind == "f":
                k = np.floor(k)
            k = k.astype(np.int32).view(np.uint32)  # two's complement bits of small integers
            h = (h + k * mult) * np.uint32(0x85EBCA77)
    return _mix32(_mix32(np.asarray(h, dtype=np.uint32)))


def hash01(*keys) -> np.ndarray:
    """Uniform float32 in [0, 1) from ``hash_u32``."""
    return (hash_u32(*keys) >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def value_noise(seed: int, channel: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth noise in [0, 1): smoothstep blend of hashed lattice values at integer (x, y)."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    ix, iy = np.floor(x), np.floor(y)
    fx, fy = x - ix, y - iy
    fx = fx * fx * (3 - 2 * fx)
    fy = fy * fy * (3 - 2 * fy)
    v00 = hash01(seed, channel, ix, iy)
    v10 = hash01(seed, channel, ix + 1, iy)
    v01 = hash01(seed, channel, ix, iy + 1)
    v11 = hash01(seed, channel, ix + 1, iy + 1)
    return ((v00 * (1 - fx) + v10 * fx) * (1 - fy) + (v01 * (1 - fx) + v11 * fx) * fy).astype(np.float32)
