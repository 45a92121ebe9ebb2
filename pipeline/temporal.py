"""Time along a sequence: the classic temporal filter and the instability metric.

Both work on images already brought into the current frame (``pipeline.motion.warp_previous``: the
previous frame's image, read with the Catmull-Rom kernel, with its validity mask), so they know nothing about
cameras. ``step`` is one frame
of a temporal method, the warp included: what ``denoise --sequence`` and the sequence evaluation both run.

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

from collections.abc import Callable

import numpy as np

from . import motion
from .config import weight_problem
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
    if (why := weight_problem(weight)) is not None:
        raise ValueError(f"blend weight: {why}")
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


def step(denoise: Callable[[dict, tuple | None], np.ndarray | None], buffers: dict[str, np.ndarray],
         view: motion.View | None, previous: tuple[np.ndarray | None, motion.View | None] | None, weight: float,
         learned: bool) -> tuple[np.ndarray | None, np.ndarray | None]:
    """One frame of a temporal method: (its output, None where ``denoise`` failed; the history's (H, W) validity,
    None without a history).

    ``previous``: (this method's output of the previous frame, that frame's view); the history is that output
    warped into ``view`` (``motion.warp_previous``), none on a first frame, after a frame that failed or
    where the two frames share no motion (``motion.linked``: motion vectors, or cameras with depth).
    ``denoise(buffers, history)`` is the per-frame method;
    ``learned``: it reads the history itself (a model with ``diffusion.history``) and its output is the frame's;
    otherwise its output without history is blended with the history (``blend_history``, ``weight``)."""
    history = None
    if (previous is not None and previous[0] is not None and view is not None and previous[1] is not None
            and motion.linked(view, previous[1])):
        history = motion.warp_previous(previous[0], view, previous[1])
    if learned:
        y = denoise(buffers, history)
    else:
        y = denoise(buffers, None)
        if y is not None and history is not None:
            y = blend_history(y, *history, weight)
    return y, None if y is None or history is None else history[1]


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
