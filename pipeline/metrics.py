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

Evaluation metrics (numpy only, float results; used by ``evaluate``):

- ``ssim``: SSIM (Wang et al. 2004) on the Reinhard tonemap, 11×11 Gaussian window σ = 1.5,
  K1 = 0.01, K2 = 0.03, dynamic range 1, "valid" positions only, mean over RGB channels.
- ``flip``: NVIDIA FLIP (``flip-evaluator``), LDR-FLIP on the Reinhard tonemap or HDR-FLIP on
  the linear radiance; lower is better, 0 for identical images.
- ``fvvdp``: FovVideoVDP (``pyfvvdp``) in JOD on the Reinhard tonemap shown on a display model
  (default ``standard_4k``); 10 for identical images, higher is better.

The colour transforms (first below): the one tonemapper module of the project: every stage maps radiance to display range here.

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
- ``linear_to_srgb``: the sRGB transfer of [0, 1] (contact sheets' self-exposed tiles), with its inverse
  ``srgb_to_linear`` (palette colours given as sRGB).

Inverses clamp their input to the tonemap's range (e.g. ``y < 1`` for Reinhard) so that a
model's slightly out-of-range prediction maps back to a finite radiance instead of inf/NaN.
"""
from __future__ import annotations

import math

import numpy as np

# ---- colour: the tonemaps and their inverses --------------------------------------------------------

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


def clamp_values(x, lo=None, hi=None):
    """``x`` limited to [lo, hi] (either bound may be None), a numpy array or a torch tensor alike."""
    if is_torch(x):
        return x.clamp(min=lo, max=hi)
    return np.clip(x, lo, hi)


def reinhard(x):
    """``max(x, 0) / (1 + max(x, 0))`` (paper eq. 7)."""
    x = clamp_values(_asarray(x), 0.0)
    return x / (1.0 + x)


def inverse_reinhard(y):
    """``y / (1 - y)`` for y clamped to [0, 1): the HDR radiance whose Reinhard value is y.

    The round trip is tested (tests/test_color_metrics.py); ``motion.warp_previous`` reads a temporal
    filter's history on Reinhard values and brings it back with it, and the metric tests build HDR
    inputs of a chosen tonemapped value with it."""
    y = clamp_values(_asarray(y), 0.0, _REINHARD_MAX)
    return y / (1.0 - y)


def log_compress(x, a: float = LOG_A):
    """``a·log(1 + max(x, 0))`` (paper eq. 5, a = 0.51)."""
    x = clamp_values(_asarray(x), 0.0)
    return a * _lib(x).log1p(x)


def inverse_log_compress(y, a: float = LOG_A):
    """``exp(y / a) - 1`` for y >= 0 (expm1 keeps small values exact)."""
    y = clamp_values(_asarray(y), 0.0)
    return _lib(y).expm1(y / a)


def gamma_compress(x, a: float = GAMMA_A, gamma: float = GAMMA):
    """``a·max(x, 0)^gamma`` (paper eq. 4, a = 0.47, gamma = 1/2.4)."""
    x = clamp_values(_asarray(x), 0.0)
    return a * x ** gamma


def inverse_gamma_compress(y, a: float = GAMMA_A, gamma: float = GAMMA):
    """``(max(y, 0) / a)^(1/gamma)``."""
    y = clamp_values(_asarray(y), 0.0)
    return (y / a) ** (1.0 / gamma)


def linear_to_srgb(x):
    """The sRGB transfer function (IEC 61966-2-1): linear RGB clamped to [0, 1] to display values.

    Lists and tuples become numpy arrays (float64); arrays and tensors keep their dtype."""
    x = clamp_values(x if is_torch(x) else np.asarray(x), 0.0, 1.0)
    return _lib(x).where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def srgb_to_linear(c):
    """The sRGB transfer function's inverse (IEC 61966-2-1): display values in [0, 1] to linear RGB.

    Lists and tuples become numpy arrays (float64); arrays and tensors keep their dtype."""
    c = c if is_torch(c) else np.asarray(c)
    return _lib(c).where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


# ---- metrics ---------------------------------------------------------------------------------------



SMAPE_EPS = 1e-2


def _mean(x):
    m = x.mean()
    return m if is_torch(x) else float(m)


def l1(pred, ref, clamp: tuple[float, float] | None = None):
    """Mean absolute error in HDR; ``clamp=(0, 6)`` clamps both images first (paper's L1)."""
    if clamp is not None:
        pred, ref = clamp_values(pred, *clamp), clamp_values(ref, *clamp)
    return _mean(abs(pred - ref))


def mse(pred, ref):
    return _mean((pred - ref) ** 2)


# Training validation averages PSNR over frames and writes it to JSON, which cannot hold inf: an
# identical frame counts as this ceiling there. The evaluation keeps inf (reported as "inf").
PSNR_CEILING = 999.0


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


SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03


def _gaussian_window(size: int, sigma: float) -> np.ndarray:
    r = np.arange(size, dtype=np.float64) - (size - 1) / 2
    g = np.exp(-r * r / (2 * sigma * sigma))
    return g / g.sum()


def _filter_valid(x: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Separable correlation of (H, W, C) ``x`` with ``g`` ⊗ ``g`` at the "valid" positions."""
    k = len(g)
    H, W = x.shape[:2]
    y = sum(g[i] * x[i:H - k + 1 + i] for i in range(k))
    return sum(g[j] * y[:, j:W - k + 1 + j] for j in range(k))


def ssim(pred, ref, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> float:
    """Mean SSIM of the Reinhard-tonemapped images (Wang et al. 2004, dynamic range L = 1).

    Local means, variances and the covariance use the normalised Gaussian window without Bessel
    correction (as the reference implementation); the SSIM map is taken at the "valid" window
    positions only (no padding) and averaged over them and the channels. Images smaller than the
    window use the largest odd window that fits (a 1×1 window compares pixel values only).
    Identical images give 1; two black images give 1 as well (C1, C2 keep the ratio defined).
    """
    x = np.asarray(reinhard(np.asarray(pred, dtype=np.float64)))
    y = np.asarray(reinhard(np.asarray(ref, dtype=np.float64)))
    if x.shape != y.shape:
        raise ValueError(f"ssim: shapes differ {x.shape} vs {y.shape}")
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    size = min(window, x.shape[0], x.shape[1])
    size -= 1 - size % 2                      # odd
    g = _gaussian_window(size, sigma)
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2
    mx, my = _filter_valid(x, g), _filter_valid(y, g)
    sxx = _filter_valid(x * x, g) - mx * mx
    syy = _filter_valid(y * y, g) - my * my
    sxy = _filter_valid(x * y, g) - mx * my
    num = (2 * mx * my + c1) * (2 * sxy + c2)
    den = (mx * mx + my * my + c1) * (sxx + syy + c2)
    return float((num / den).mean())


# Luminance weights of linear sRGB (D65): FLIP's reference Y decides its exposures; contact sheets expose by it.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def flip(pred, ref, hdr: bool = False) -> float:
    """Mean FLIP error (NVIDIA ``flip-evaluator``) of ``pred`` against ``ref``, HDR radiance inputs.

    ``hdr=False``: LDR-FLIP of the Reinhard tonemaps (displayed values, sRGB-encoded as FLIP
    assumes). ``hdr=True``: HDR-FLIP of the radiance clamped at 0 (linear sRGB), with FLIP's own
    exposure range from the reference — except for an all-black reference, where FLIP's start
    exposure is log2(x/0) and its C++ core terminates the process: there one exposure (0) is
    used, i.e. LDR-FLIP of the ACES-tonemapped images.
    """
    import flip_evaluator

    params = {}
    if hdr:
        r = np.ascontiguousarray(np.clip(np.asarray(ref, dtype=np.float32), 0, None))
        t = np.ascontiguousarray(np.clip(np.asarray(pred, dtype=np.float32), 0, None))
        if float((r.reshape(-1, 3) @ LUMINANCE).max(initial=0.0)) <= 0.0:
            params = {"startExposure": 0.0, "stopExposure": 0.0}
    else:
        r = np.ascontiguousarray(reinhard(np.asarray(ref, dtype=np.float32)), dtype=np.float32)
        t = np.ascontiguousarray(reinhard(np.asarray(pred, dtype=np.float32)), dtype=np.float32)
    _, mean, _ = flip_evaluator.evaluate(r, t, "HDR" if hdr else "LDR", applyMagma=False, parameters=params)
    return float(mean)


_FVVDP: dict = {}


def fvvdp(pred, ref, display: str = "standard_4k") -> float:
    """FovVideoVDP quality in JOD (10 = no visible difference) of the Reinhard tonemaps as still images.

    The tonemapped values are treated as display-encoded pixel values of the ``display`` model
    (``standard_4k``: 200 cd/m², sRGB), as the paper's evaluation does. Runs on the CPU, offline
    (the package ships its parameters and CSF tables).
    """
    import warnings

    import torch

    if display not in _FVVDP:
        with warnings.catch_warnings():      # pyfvvdp 1.2.2 uses scipy.io names deprecated in SciPy 1.8+
            warnings.simplefilter("ignore", DeprecationWarning)
            import pyfvvdp
            _FVVDP[display] = pyfvvdp.fvvdp(display_name=display, heatmap=None, device=torch.device("cpu"))
    r = np.ascontiguousarray(reinhard(np.asarray(ref, dtype=np.float32)), dtype=np.float32)
    t = np.ascontiguousarray(reinhard(np.asarray(pred, dtype=np.float32)), dtype=np.float32)
    with torch.no_grad():
        q, _ = _FVVDP[display].predict(t, r, dim_order="HWC")
    return float(q)


def fvvdp_video(preds, refs, display: str = "standard_4k", fps: float = 24.0) -> float:
    """FovVideoVDP quality in JOD of a sequence watched as a video at ``fps`` (lists of (H, W, 3) HDR frames,
    Reinhard-tonemapped as ``fvvdp``): flicker between frames counts, as a viewer sees it."""
    import torch

    fvvdp(preds[0], refs[0], display)                 # builds (and caches) the model for the display
    t = np.ascontiguousarray(np.stack([reinhard(np.asarray(p, np.float32)) for p in preds]), dtype=np.float32)
    r = np.ascontiguousarray(np.stack([reinhard(np.asarray(x, np.float32)) for x in refs]), dtype=np.float32)
    with torch.no_grad():
        q, _ = _FVVDP[display].predict(t, r, dim_order="FHWC", frames_per_second=fps)
    return float(q)


def all_metrics(pred, ref, eps: float = SMAPE_EPS) -> dict[str, float]:
    """``{"psnr", "l1", "smape"}`` as floats (numpy or torch inputs)."""
    if is_torch(pred):
        pred, ref = pred.detach().double().cpu().numpy(), ref.detach().double().cpu().numpy()
    pred, ref = np.asarray(pred, dtype=np.float64), np.asarray(ref, dtype=np.float64)
    return {"psnr": psnr(pred, ref), "l1": l1(pred, ref, clamp=(0.0, 6.0)), "smape": smape(pred, ref, eps)}
