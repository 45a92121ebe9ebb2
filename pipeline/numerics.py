"""Small numerical helpers shared by the stages: non-finite repair, over-long normals, constant detection."""
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


def shorten_normals(normal: np.ndarray, limit: float = 1.01) -> int:
    """Scale normals longer than ``limit`` to unit length, in place; returns how many pixels. A rendered normal
    has length 1 (0 where nothing was hit) and is left alone bit for bit; one of length 1e3 (another renderer's
    unnormalised or garbage layer) would otherwise reach a network as an input 1000x beyond its training."""
    length = np.sqrt(np.sum(np.square(normal, dtype=np.float64), axis=-1))
    long = length > limit
    if long.any():
        normal[long] = (normal[long] / length[long][:, None]).astype(normal.dtype)
    return int(long.sum())


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
