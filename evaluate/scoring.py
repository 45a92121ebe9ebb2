"""The metric columns of the evaluation tables, on top of ``pipeline.metrics`` (one definition each).

Every metric compares a method's HDR output with the reference (GT_clean) of the same frame:

| key | column | better | definition |
| --- | --- | --- | --- |
| l1 | L1 | lower | mean abs. difference in HDR, both clamped to [0, 6] |
| psnr | PSNR dB | higher | on x/(1+x), peak 1; inf for identical images |
| ssim | SSIM | higher | Wang et al. 2004 on x/(1+x) |
| flip | FLIP | lower | LDR-FLIP on x/(1+x) |
| hdr_flip | HDR-FLIP | lower | HDR-FLIP on the radiance |
| fvvdp | FovVideoVDP | higher | JOD on x/(1+x), display model eval.fvvdp_display |

LPIPS, DINO and CLIP (paper Table 1) need network weights that cannot be fetched here; they are
not computed (and no number is made up for them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from mcdenoise.pipeline import metrics
from mcdenoise.pipeline.config import ConfigError


@dataclass(frozen=True)
class Metric:
    key: str
    column: str
    higher_is_better: bool
    fn: Callable
    needs: str | None = None      # optional package it imports

    @property
    def arrow(self) -> str:
        return "↑" if self.higher_is_better else "↓"


METRICS: dict[str, Metric] = {m.key: m for m in (
    Metric("l1", "L1", False, lambda p, r, o: metrics.l1(p, r, clamp=(0.0, 6.0))),
    Metric("psnr", "PSNR dB", True, lambda p, r, o: metrics.psnr(p, r)),
    Metric("ssim", "SSIM", True, lambda p, r, o: metrics.ssim(p, r)),
    Metric("flip", "FLIP", False, lambda p, r, o: metrics.flip(p, r, hdr=False), "flip_evaluator"),
    Metric("hdr_flip", "HDR-FLIP", False, lambda p, r, o: metrics.flip(p, r, hdr=True), "flip_evaluator"),
    Metric("fvvdp", "FovVideoVDP JOD", True, lambda p, r, o: metrics.fvvdp(p, r, o.get("display", "standard_4k")),
           "pyfvvdp"),
)}
NOT_COMPUTED = {"LPIPS, DINO, CLIP": "need pretrained network weights, which cannot be downloaded here; "
                                     "not computed"}


def check_metrics(names: list[str]) -> None:
    unknown = [n for n in names if n not in METRICS]
    if unknown:
        raise ConfigError(f"eval.metrics: unknown metric {unknown[0]!r} (known: {', '.join(METRICS)})")


def usable_metrics(names: list[str]) -> tuple[list[str], dict[str, str]]:
    """(metrics that can run here, {metric: why not}) — a missing optional package is a reason."""
    import importlib

    ok, missing = [], {}
    for name in names:
        needs = METRICS[name].needs
        if needs:
            try:
                importlib.import_module(needs)
            except ImportError as exc:
                missing[name] = f"{needs} is not installed ({exc})"
                continue
        ok.append(name)
    return ok, missing


def score(pred, ref, names: list[str], options: dict | None = None) -> dict[str, float]:
    """{metric: value} of ``pred`` against ``ref`` (HDR, (H, W, 3), finite)."""
    options = options or {}
    return {name: float(METRICS[name].fn(pred, ref, options)) for name in names}


def best(values: dict[str, float], key: str) -> set[str]:
    """Rows holding the best finite-or-inf value of metric ``key`` (ties all win)."""
    vals = {k: v for k, v in values.items() if v is not None and not math.isnan(v)}
    if not vals:
        return set()
    target = max(vals.values()) if METRICS[key].higher_is_better else min(vals.values())
    return {k for k, v in vals.items() if v == target}
