"""Small numerical helpers shared by the stages: non-finite repair, constant detection."""
from __future__ import annotations

import numpy as np


def repair_nonfinite(arrays: dict[str, np.ndarray]) -> dict[str, int]:
    """Replace NaN/±Inf by 0 in place and return the number of bad values per key.

    Called on every rendered image before it is stored, so NaN/Inf never reach the store
    silently: the counts go into the EXR header and the manifests and are reported by
    ``inspect`` and in the render summary. Zero is the repair because a lost sample contributes
    nothing; the pixel keeps the other channels' values. Only keys with a non-zero count appear.
    """
    counts: dict[str, int] = {}
    for key, arr in arrays.items():
        bad = ~np.isfinite(arr)
        n = int(bad.sum())
        if n:
            arr[bad] = 0.0
            counts[key] = n
    return counts


def constant_value(arr: np.ndarray) -> float | None:
    """The single value of ``arr`` if every element equals it exactly, else None."""
    if arr.size == 0:
        return None
    flat = arr.reshape(-1)
    first = flat[0]
    if np.isnan(first):
        return None
    if np.all(flat == first):
        return float(first)
    return None


def sample_variance_of_mean(m1: np.ndarray, m2: np.ndarray, n: int) -> np.ndarray:
    """Variance of the pixel mean from the first and second sample moments over ``n`` samples.

    Unbiased per-sample variance s² = n/(n-1)·(E[x²] − E[x]²), divided by n; clamped at 0
    because round-off makes E[x²] − E[x]² slightly negative for (near-)constant pixels.
    """
    if n < 2:
        return np.zeros_like(m1, dtype=np.float32)
    m1 = m1.astype(np.float64)
    var = (m2.astype(np.float64) - m1 * m1) / (n - 1)
    return np.maximum(var, 0.0).astype(np.float32)
