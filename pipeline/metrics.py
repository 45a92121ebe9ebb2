"""Image error metrics, shared by the cleaner, the trainers and the evaluator.

Each function takes numpy arrays or torch tensors (``pred``, ``ref`` of the same shape, HDR
radiance) and returns a Python float (numpy) or a 0-d tensor (torch, differentiable where that
makes sense). The formulas use only operations both libraries have, so there is one definition
of each metric; ``clean.losses`` trains with the very same ``smape``.

- ``l1``: mean |pred - ref| in HDR (the paper's L1, "computed in HDR [0 - 6] space"): with
  ``clamp=(0, 6)`` both images are clamped to [0, 6] first.
- ``psnr``: on the ``clamp(x, 0)/(1 + x)`` tonemap (paper eq. 7) with peak 1:
  ``10·log10(1 / MSE)``; identical images give ``inf``.
- ``smape``: symmetric mean absolute percentage error, per pixel and channel (see ``smape``).
"""
from __future__ import annotations

import math

import numpy as np

from .color import _clamp, _is_torch, reinhard

SMAPE_EPS = 1e-2


def _mean(x):
    m = x.mean()
    return m if _is_torch(x) else float(m)


def l1(pred, ref, clamp: tuple[float, float] | None = None):
    """Mean absolute error in HDR; ``clamp=(0, 6)`` clamps both images first (paper's L1)."""
    if clamp is not None:
        pred, ref = _clamp(pred, *clamp), _clamp(ref, *clamp)
    return _mean(abs(pred - ref))


def mse(pred, ref):
    return _mean((pred - ref) ** 2)


def psnr(pred, ref) -> float:
    """PSNR in dB of the Reinhard-tonemapped images, peak 1; ``inf`` when they are identical."""
    err = float(mse(reinhard(pred), reinhard(ref)))
    if err == 0.0:
        return math.inf
    return 10.0 * math.log10(1.0 / err)


def smape(pred, ref, eps: float = SMAPE_EPS):
    """SMAPE, the paper's eq. 2 evaluated per pixel and channel and averaged:

        mean over pixels p and channels c of |A_pc - B_pc| / (|A_pc| + |B_pc| + eps).

    Eq. 2 written with image-wide L1 norms would let the brightest pixels dominate an HDR image;
    the per-element form (the one of the KPCN / Isik et al. re-implementations) is relative in
    every pixel, so a dark corner counts as much as a light source. Each term lies in [0, 1],
    which keeps it finite for all-zero pixels (0 / eps) and for radiance 1e5 alike.
    ``eps`` (default 1e-2, ``clean.smape_eps``) sets the radiance below which errors count as
    absolute rather than relative: it stops near-black pixels, whose relative error is pure
    noise, from dominating.
    """
    return _mean(abs(pred - ref) / (abs(pred) + abs(ref) + eps))


def all_metrics(pred, ref, eps: float = SMAPE_EPS) -> dict[str, float]:
    """``{"psnr", "l1", "smape"}`` as floats (numpy or torch inputs)."""
    if _is_torch(pred):
        pred, ref = pred.detach().double().cpu().numpy(), ref.detach().double().cpu().numpy()
    pred, ref = np.asarray(pred, dtype=np.float64), np.asarray(ref, dtype=np.float64)
    return {"psnr": psnr(pred, ref), "l1": l1(pred, ref, clamp=(0.0, 6.0)), "smape": smape(pred, ref, eps)}
