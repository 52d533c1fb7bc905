"""Thinning returns to a budget without aliasing the scan pattern."""

from __future__ import annotations

import numpy as np


def random_subset(idx: np.ndarray, k: int, seed: int) -> np.ndarray:
    """``k`` of ``idx`` (all when fewer) drawn at random without replacement, kept in their
    order; seeded, so the same on every call. Every k-th element instead would keep one sector
    of every profile whenever the stride divides a profile's returns."""
    if idx.size <= k:
        return idx
    drawn = np.random.default_rng(seed).choice(idx.size, k, replace=False)
    drawn.sort()
    return idx[drawn]
