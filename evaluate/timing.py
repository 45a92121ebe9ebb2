"""Render-time model, equal-time sample counts and the sample count a method is worth.

Render cost of a frame (``render_cost``): ``t(N) = a + b·N`` seconds for one render at N spp,
fitted per frame from the per-image render seconds of its ``frame.json`` (recorded by the
renderer): the low-spp stacks (``stack_spp`` each, median over the stacks) and the ground truths
(``gt_spp``, the faster of GT1/GT2, since the first image of a scene can include the JIT compile).
``b`` is the marginal cost of one sample per pixel, ``a`` the fixed cost of a render call.

Equal time (``equal_time_spp``): a denoiser that takes ``t_d`` seconds on an ``s``-spp input
costs ``t(s) + t_d``; plain Monte Carlo gets as much with ``N = s + t_d / b`` samples (``a``
cancels). The evaluator renders that N (or pools stored stacks up to their total, see
``evaluate.run``).

Worth in samples (``spp_equivalent``): the sample count at which plain Monte Carlo reaches a
given error, by piecewise-linear interpolation of log(error) against log(spp) on the measured MC
curve; outside the measured range the end segment's slope is extended and the result is marked
as extrapolated, at most ``MAX_EXTRAPOLATION``× past the curve's ends (further out the end slope
says nothing: a nearly flat segment would put a method at 1e20 spp); beyond that the answer is
"more than" that bound, without a number.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

_STACK = re.compile(r"^s\d+$")
MAX_EXTRAPOLATION = 16.0


@dataclass(frozen=True)
class RenderCost:
    a: float          # seconds per render call, independent of spp
    b: float          # seconds per sample per pixel
    how: str          # "fit" (stacks + GT) or "proportional" (one sample count only, a = 0)

    def seconds(self, spp: float) -> float:
        return self.a + self.b * float(spp)


def render_cost(record: dict) -> RenderCost:
    """Fit ``t(N) = a + b·N`` to one frame record's per-image ``render_seconds`` and ``spp``."""
    stacks, gts = [], []
    for name, img in record.get("images", {}).items():
        t, spp = img.get("render_seconds"), img.get("spp")
        if t is None or not spp:
            continue
        if _STACK.match(name):
            stacks.append((float(spp), float(t)))
        elif name in ("gt1", "gt2"):
            gts.append((float(spp), float(t)))
    if not stacks and not gts:
        raise ValueError("frame record has no render_seconds: cannot model the render time")
    if stacks and gts:
        n_lo, t_lo = stacks[0][0], float(np.median([t for _, t in stacks]))
        n_hi, t_hi = min(gts, key=lambda g: g[1])   # the faster GT with its own spp (progressive GTs differ)
        if n_hi > n_lo and t_hi > t_lo:
            b = (t_hi - t_lo) / (n_hi - n_lo)
            return RenderCost(max(0.0, t_lo - b * n_lo), b, "fit")
    n, t = (gts or stacks)[0][0], min(t for _, t in (gts or stacks))
    return RenderCost(0.0, t / n, "proportional")


def equal_time_spp(spp: int, denoise_seconds: float, cost: RenderCost) -> float:
    """Samples per pixel plain MC renders in the time of an ``spp`` render plus the denoiser."""
    return float(spp) + max(0.0, float(denoise_seconds)) / cost.b


def spp_equivalent(spps, errors, target: float) -> tuple[float | None, str]:
    """Sample count at which the MC curve (``spps``, ``errors``; lower is better) reaches ``target``.

    Returns (spp, how): how is "interpolated", "extrapolated below <lowest spp>",
    "extrapolated beyond <highest spp>", or, with spp None, why there is no answer (the curve
    does not decrease there; the target or the curve is not positive and finite). A target of
    exactly 0 (a perfect image) is "unreachable".
    """
    pts = sorted((float(n), float(e)) for n, e in zip(spps, errors) if math.isfinite(e) and e > 0 and n > 0)
    if not math.isfinite(target) or target < 0:
        return None, "no finite target error"
    if target == 0:
        return None, "unreachable: zero error"
    if len(pts) < 2:
        return None, "MC curve has fewer than two points"
    x = [math.log(n) for n, _ in pts]
    y = [math.log(e) for _, e in pts]
    ly = math.log(target)
    for i in range(len(pts) - 1):
        if (y[i] - ly) * (y[i + 1] - ly) <= 0:
            if y[i] == y[i + 1]:
                return math.exp(x[i]), "interpolated"
            return math.exp(x[i] + (ly - y[i]) * (x[i + 1] - x[i]) / (y[i + 1] - y[i])), "interpolated"
    if ly > max(y):
        i, where = 0, f"extrapolated below {pts[0][0]:g} spp"
    else:
        i, where = len(pts) - 2, f"extrapolated beyond {pts[-1][0]:g} spp"
    slope = (y[i + 1] - y[i]) / (x[i + 1] - x[i])
    if slope >= 0:
        return None, "not reached: the MC curve does not decrease there"
    j = 0 if i == 0 else i + 1
    value = math.exp(x[j] + (ly - y[j]) / slope)
    if value > pts[-1][0] * MAX_EXTRAPOLATION:
        return None, f"more than {pts[-1][0] * MAX_EXTRAPOLATION:g} spp ({MAX_EXTRAPOLATION:g}x past the MC curve)"
    if value < pts[0][0] / MAX_EXTRAPOLATION:
        return None, f"less than {pts[0][0] / MAX_EXTRAPOLATION:g} spp ({MAX_EXTRAPOLATION:g}x below the MC curve)"
    return value, where


def psnr_to_mse(psnr: float) -> float:
    """The tonemapped MSE of a PSNR (peak 1): the error spp_equivalent interpolates for PSNR."""
    return 0.0 if psnr == math.inf else 10.0 ** (-psnr / 10.0)
