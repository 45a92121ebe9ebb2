"""Time along a sequence: the classic temporal filter and the instability metric.

Both work on images already brought into the current frame (``pipeline.motion.warp`` of the
previous frame with its validity mask), so they know nothing about cameras.

**The temporal filter** (``blend_history``) is what a renderer's TAA or a compositor's temporal
denoise node does with a per-frame denoiser's outputs: an exponential moving average

    h_t = w · y_t + (1 − w) · clamp(warp(h_{t−1}))      where the history is valid,
    h_t = y_t                                           elsewhere (first frame, off-screen, disoccluded),

with the history clamped, per channel, to the range of the current output's 3×3 neighbourhood
(Karis 2014, "High-quality temporal supersampling"). The clamp is what keeps a long history from
smearing: without it, a wrong history (a reprojection error, a moving highlight) never leaves.

**Temporal instability** (``instability``) measures flicker against the reference: over the pixels
valid in both frames, the mean absolute difference between the output's frame-to-frame change and
the reference's, each tonemapped (x/(1+x), the metrics' tonemap):

    I_t = mean_valid | (T(y_t) − T(warp(y_{t−1}))) − (T(r_t) − T(warp(r_{t−1}))) |

A denoiser whose error is the same in both frames (it follows the image) scores 0 however large
that error; noise that changes from frame to frame scores about its mean absolute size. Subtracting
the reference's change removes what legitimately changes (view-dependent shading, the reprojection's
own resampling), so a still, perfect sequence and a moving, perfect one both score 0.
"""
from __future__ import annotations

import numpy as np

from .metrics import reinhard


def neighbourhood_range(image: np.ndarray, radius: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel and channel, the minimum and maximum of ``image`` over its (2·radius+1)² neighbourhood
    (edge pixels: the part of the window inside the image)."""
    h, w = image.shape[:2]
    pad = np.pad(image, ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    lo, hi = image.copy(), image.copy()
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            window = pad[dy:dy + h, dx:dx + w]
            np.minimum(lo, window, out=lo)
            np.maximum(hi, window, out=hi)
    return lo, hi


def blend_history(current: np.ndarray, history: np.ndarray | None, valid: np.ndarray | None, weight: float,
                  clamp: bool = True) -> np.ndarray:
    """One step of the temporal filter: ``current`` (H, W, C) blended with ``history`` (the filter's
    previous output warped into this frame) where ``valid``; ``weight`` is the new frame's share (1: no
    history). ``history`` None (the first frame) returns ``current`` unchanged."""
    if not 0.0 < weight <= 1.0:
        raise ValueError(f"blend weight must be in (0, 1], got {weight}")
    current = np.asarray(current, dtype=np.float32)
    if history is None:
        return current.copy()
    if history.shape != current.shape or valid is None or valid.shape != current.shape[:2]:
        raise ValueError(f"history {getattr(history, 'shape', None)} / valid {getattr(valid, 'shape', None)} "
                         f"do not match the frame {current.shape}")
    past = np.asarray(history, dtype=np.float32)
    if clamp:
        lo, hi = neighbourhood_range(current)
        past = np.clip(past, lo, hi)
    out = current.copy()
    keep = valid.astype(bool)
    out[keep] = weight * current[keep] + (1.0 - weight) * past[keep]
    return out


def instability(output: np.ndarray, output_prev_warped: np.ndarray, reference: np.ndarray,
                reference_prev_warped: np.ndarray, valid: np.ndarray) -> float:
    """Temporal instability of ``output`` at one frame (see the module docstring); NaN when no pixel is
    valid. All images (H, W, C) linear HDR, the previous frames already warped into this one."""
    keep = np.asarray(valid, dtype=bool)
    if not keep.any():
        return float("nan")
    change = reinhard(np.asarray(output, np.float64)) - reinhard(np.asarray(output_prev_warped, np.float64))
    truth = reinhard(np.asarray(reference, np.float64)) - reinhard(np.asarray(reference_prev_warped, np.float64))
    return float(np.abs(change - truth)[keep].mean())
