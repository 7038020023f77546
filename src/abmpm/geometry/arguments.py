"""Checks of the numeric arguments of the geometry builders.

Each returns the value as a number (or a float64 array) and raises ``ValueError``
naming the argument when it is not acceptable.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["non_negative", "positive", "vec3"]


def vec3(value, name: str) -> np.ndarray:
    """Three finite numbers as a float64 ``(3,)`` array."""
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be three finite numbers, got {value!r}")
    return v


def positive(value, name: str) -> float:
    """A finite number greater than zero."""
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return v


def non_negative(value, name: str) -> float:
    """A finite number at least zero."""
    v = float(value)
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"{name} must be a non-negative number, got {value!r}")
    return v
