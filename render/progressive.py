"""Ground truth rendered progressively to a target error (``dataset.gt_target_psnr``).

A ground truth (GT1 or GT2) is rendered in passes of ``pass_spp`` samples. Pass k uses the seed
``pass_seed(image seed, k)``, and the passes are pooled with the exact statistics of
``pipeline.store.combine_stacks`` (the running estimate of k·n samples with the new pass of n): the
mean and the variance of the mean are those of all the samples taken together. After each pass the
error of the mean is estimated (``estimated_psnr``); the image stops at the first pass where the
estimate reaches the target, or at ``max_spp``.

Equivalence with one render: Mitsuba's sampler stream depends on the render's spp (the wavefront
size), so k passes of n spp are not bit-identical to one render of k·n spp with any seed. They are
the same estimator: k·n independent samples, pooled mean and unbiased variance of the mean
(tests/test_progressive.py checks that the two agree within their variances on a real scene).

GT1 and GT2 each follow the rule on their own (they may stop at different spp); the seeds are fixed
by the image seed, so a killed frame re-renders to the identical image.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from mcdenoise.pipeline.store import combine_stacks


@dataclass(frozen=True)
class StopRule:
    target_psnr: float | None   # None: one render of max_spp (the fixed gt_spp)
    pass_spp: int
    max_spp: int


@dataclass
class ProgressiveResult:
    buffers: dict[str, np.ndarray]
    constants: dict[str, float]
    nonfinite: dict[str, int]
    seconds: float                                # render time (with a target: all passes, pooling included)
    spp: int
    passes: int
    estimated_psnr: float
    history: list = field(default_factory=list)   # (spp, estimated PSNR) after each pass


def pass_seed(seed: int, k: int) -> int:
    """The 32-bit seed of pass ``k`` of an image with seed ``seed``; pass 0 uses the image's own seed
    (a one-pass GT is today's single render). Later passes hash (seed, k), so they are independent
    streams, the same on every run."""
    if k == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), int(k)]).generate_state(1, np.uint32)[0])


def estimated_mse(color: np.ndarray, variance: np.ndarray) -> float:
    """Expected squared error of the mean against the true image on the metric's tonemap
    T(x) = max(x, 0)/(1 + max(x, 0)) (``pipeline.metrics.reinhard``), by the delta method:
    mean over pixels and channels of T'(m)²·Var(m), with T'(m) = 1/(1 + max(m, 0))²."""
    m = np.maximum(color.astype(np.float64), 0.0)
    return float(np.mean(variance.astype(np.float64) / (1.0 + m) ** 4))


def estimated_psnr(color: np.ndarray, variance: np.ndarray) -> float:
    """PSNR in dB (peak 1, as ``pipeline.metrics.psnr``) that the mean is expected to have against
    the true image; ``inf`` for a zero variance. Two independent images of estimates P1 and P2 are
    expected to differ by -10·log10(10^(-P1/10) + 10^(-P2/10)) dB (3 dB below P for equal ones)."""
    mse = estimated_mse(color, variance)
    return math.inf if mse <= 0.0 else 10.0 * math.log10(1.0 / mse)


def expected_spp(psnr: float, spp: int, rule: StopRule) -> int:
    """The spp at which an image whose estimate is ``psnr`` at ``spp`` samples is expected to stop:
    the error of the mean falls as 1/spp, so the estimate gains 10·log10(2) dB per doubling; the first
    multiple of ``pass_spp`` at or above the target, capped at ``max_spp``."""
    if rule.target_psnr is None:
        return rule.max_spp
    need = spp * 10.0 ** ((rule.target_psnr - psnr) / 10.0)
    passes = max(1, math.ceil(need / rule.pass_spp - 1e-9))
    return min(passes * rule.pass_spp, rule.max_spp)


def render_to_target(render_pass: Callable, seed: int, rule: StopRule) -> ProgressiveResult:
    """Render one image by ``rule``. ``render_pass(spp, seed)`` returns a ``render.buffers.RenderResult``.

    Without a target: one pass of ``max_spp`` with ``seed``. With one: passes of ``pass_spp`` pooled
    exactly until the estimated PSNR of ``color`` reaches the target or the next pass would exceed
    ``max_spp``.
    """
    if rule.target_psnr is None:
        r = render_pass(rule.max_spp, seed)
        est = estimated_psnr(r.buffers["color"], r.buffers["color.variance"])
        return ProgressiveResult(r.buffers, r.constants, dict(r.nonfinite), r.seconds, rule.max_spp, 1, est,
                                 [(rule.max_spp, est)])
    acc, spp, nonfinite, history = None, 0, {}, []
    constants: dict = {}
    t0 = time.perf_counter()   # the pooling and the estimates are part of a progressive GT's cost
    while True:
        r = render_pass(rule.pass_spp, pass_seed(seed, len(history)))
        for key, n in r.nonfinite.items():
            nonfinite[key] = nonfinite.get(key, 0) + n
        if acc is None:
            acc, constants = r.buffers, r.constants
        else:
            acc = combine_stacks([acc, r.buffers], [spp, rule.pass_spp])
        spp += rule.pass_spp
        est = estimated_psnr(acc["color"], acc["color.variance"])
        history.append((spp, est))
        if est >= rule.target_psnr or spp + rule.pass_spp > rule.max_spp:
            return ProgressiveResult(acc, constants, nonfinite, time.perf_counter() - t0, spp, len(history), est,
                                     history)
