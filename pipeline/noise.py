"""Is the noise of an image independent from pixel to pixel? (``denoise --exr``'s input check.)

OIDN, and every denoiser here that starts from it, expects each sample to land in one pixel (a box
reconstruction filter, as this project's renderer uses). A wide filter (Mitsuba's default
``gaussian``, ``tent``) splats each sample over its neighbours, the noise becomes spatially
correlated, and OIDN leaves it in place: on Mitsuba's Cornell box at 4 spp OIDN gains +10.8 dB
on a box-filtered render and +0.1 dB on a Gaussian-filtered one (docs/diffusion.md).

``neighbour_ratio`` measures it without a reference. A second difference (x[i-k] - 2 x[i] + x[i+k])
cancels any linear trend of the image; over independent noise it has the same spread at k = 1 and
k = 2, while correlated noise makes neighbours alike and shrinks the k = 1 one. The spreads are
medians of absolute second differences of log(1 + luminance) along rows and columns, robust to
edges and fireflies. Measured on Mitsuba's Cornell box (96², with and without a glass sphere), at
1-256 spp: 0.82-0.93 with a box filter, 0.56-0.65 with ``gaussian``, 0.62-0.72 with ``tent``. A nearly
noise-free image reads low whatever the filter (at 4096 spp the box filter reads 0.69-0.75): there
the signal's own curvature dominates, and there is little noise left to remove anyway.
"""
from __future__ import annotations

import numpy as np

CORRELATED_BELOW = 0.77   # box filter at 1-256 spp: >= 0.82; gaussian and tent: <= 0.72


def _log_luminance(color: np.ndarray) -> np.ndarray:
    return np.log1p(np.maximum(np.nan_to_num(np.asarray(color, np.float64)), 0).mean(-1))


def _second_differences(y: np.ndarray, k: int) -> np.ndarray:
    rows = y[:, 2 * k:] - 2 * y[:, k:-k] + y[:, :-2 * k]
    cols = y[2 * k:] - 2 * y[k:-k] + y[:-2 * k]
    return np.concatenate([rows.ravel(), cols.ravel()])


def neighbour_ratio(color: np.ndarray) -> float | None:
    """Median |second difference at lag 1| over median |second difference at lag 2| of log(1 + luminance),
    rows and columns pooled; None when the image is too small or flat to tell."""
    y = _log_luminance(color)
    if min(y.shape) < 5:
        return None
    lag2 = float(np.median(np.abs(_second_differences(y, 2))))
    return float(np.median(np.abs(_second_differences(y, 1)))) / lag2 if lag2 > 0 else None


def correlated_noise(color: np.ndarray) -> float | None:
    """The ratio when it says the noise is spatially correlated (below ``CORRELATED_BELOW``), else None."""
    r = neighbour_ratio(color)
    return r if r is not None and r < CORRELATED_BELOW else None
