"""The one tonemapper module of the project: every stage maps radiance to display range here.

All functions take numpy arrays or torch tensors and return the same kind (the ops used exist in
both libraries), so the diffusion model, the cleaner, the evaluator and the plots share one
definition. Radiance is clamped at 0 first: a path tracer's radiance is non-negative, and the
evaluator's ``clamp(x, 0)/(1 + x)`` convention (the authors' code) does the same.

- ``reinhard``: ``x / (1 + x)`` (paper eq. 7), the tonemap of PSNR and the perceptual metrics.
  Maps [0, inf) onto [0, 1); its inverse ``y / (1 - y)`` is defined on [0, 1).
- ``log_compress``: ``A·log(1 + x)``, A = 0.51 (paper eq. 5), the diffusion model's space;
  6 maps to 0.99, so the paper's [0, 6] range lands in [0, 1].
- ``gamma_compress``: ``A·x^γ``, A = 0.47, γ = 1/2.4 (paper eq. 4), used for figures;
  6 maps to 0.99 as well.

Inverses clamp their input to the tonemap's range (e.g. ``y < 1`` for Reinhard) so that a
model's slightly out-of-range prediction maps back to a finite radiance instead of inf/NaN.
"""
from __future__ import annotations

import numpy as np

LOG_A = 0.51
GAMMA_A = 0.47
GAMMA = 1.0 / 2.4
# Largest tonemapped value the Reinhard inverse accepts: 1 - 2^-24 maps back to ~1.7e7.
_REINHARD_MAX = 1.0 - 2.0 ** -24


def is_torch(x) -> bool:
    """Whether ``x`` is a torch tensor (without importing torch)."""
    return type(x).__module__.startswith("torch")


def _lib(x):
    if is_torch(x):
        import torch
        return torch
    return np


def _asarray(x):
    return x if is_torch(x) or isinstance(x, np.ndarray) else np.asarray(x, dtype=np.float64)


def clamp(x, lo=None, hi=None):
    """``x`` limited to [lo, hi] (either bound may be None), a numpy array or a torch tensor alike."""
    if is_torch(x):
        return x.clamp(min=lo, max=hi)
    return np.clip(x, lo, hi)


def reinhard(x):
    """``max(x, 0) / (1 + max(x, 0))`` (paper eq. 7)."""
    x = clamp(_asarray(x), 0.0)
    return x / (1.0 + x)


def inverse_reinhard(y):
    """``y / (1 - y)`` for y clamped to [0, 1): the HDR radiance whose Reinhard value is y.

    No stage calls it: Reinhard is a tonemap of the losses and metrics, and every such transform has
    its inverse here with the round trip tested (tests/test_color_metrics.py); the metric tests build
    HDR inputs of a chosen tonemapped value with it."""
    y = clamp(_asarray(y), 0.0, _REINHARD_MAX)
    return y / (1.0 - y)


def log_compress(x, a: float = LOG_A):
    """``a·log(1 + max(x, 0))`` (paper eq. 5, a = 0.51)."""
    x = clamp(_asarray(x), 0.0)
    return a * _lib(x).log1p(x)


def inverse_log_compress(y, a: float = LOG_A):
    """``exp(y / a) - 1`` for y >= 0 (expm1 keeps small values exact)."""
    y = clamp(_asarray(y), 0.0)
    return _lib(y).expm1(y / a)


def gamma_compress(x, a: float = GAMMA_A, gamma: float = GAMMA):
    """``a·max(x, 0)^gamma`` (paper eq. 4, a = 0.47, gamma = 1/2.4)."""
    x = clamp(_asarray(x), 0.0)
    return a * x ** gamma


def inverse_gamma_compress(y, a: float = GAMMA_A, gamma: float = GAMMA):
    """``(max(y, 0) / a)^(1/gamma)``."""
    y = clamp(_asarray(y), 0.0)
    return (y / a) ** (1.0 / gamma)


def srgb_to_linear(c):
    """The sRGB transfer function's inverse (IEC 61966-2-1): display values in [0, 1] to linear RGB.

    Lists and tuples become numpy arrays (float64); arrays and tensors keep their dtype."""
    c = c if is_torch(c) else np.asarray(c)
    return _lib(c).where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
