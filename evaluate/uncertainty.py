"""How well a denoiser's own per-pixel uncertainty predicts its actual error (``ours_kN``: the standard
deviation of its N samples, ``denoise --samples N``'s ``std`` layer).

Per frame, with s the predicted standard deviation and e = |output − reference| (HDR, both averaged
over R, G, B):

- **rank correlation**: Spearman's ρ between s and e over the frame's pixels (``scipy.stats``): 1 when
  the pixels the denoiser is least sure of are exactly those it gets most wrong, 0 when s says
  nothing about e;
- **calibration**: pixels pooled over frames and binned by s (equal-count bins); per bin the mean s
  and the root-mean-square error. A calibrated σ lies on the diagonal; above it the denoiser is
  over-confident. A method whose samples all agree (σ = 0 everywhere) has no curve;
- **coverage**: the fraction of pooled pixels whose error is within 1σ and within 2σ (a Gaussian
  error with standard deviation σ: 68.3 % and 95.4 %).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from mcdenoise.pipeline.figures import save_figure


def pixel_pairs(std: np.ndarray, output: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(predicted σ, absolute error) per pixel, channel means, flattened."""
    s = np.asarray(std, np.float64).mean(axis=2).ravel()
    e = np.abs(np.asarray(output, np.float64) - np.asarray(reference, np.float64)).mean(axis=2).ravel()
    return s, e


def rank_correlation(s: np.ndarray, e: np.ndarray) -> float | None:
    """Spearman's ρ of σ and error; None when either is constant (no ranking to compare)."""
    from scipy.stats import spearmanr

    if np.ptp(s) == 0 or np.ptp(e) == 0:
        return None
    return float(spearmanr(s, e).statistic)


def calibration(s: np.ndarray, e: np.ndarray, bins: int = 10) -> list[dict]:
    """Equal-count bins of σ: mean σ, RMS error and pixel count per bin."""
    order = np.argsort(s, kind="stable")
    out = []
    for part in np.array_split(order, min(bins, len(order))):
        if len(part):
            out.append({"std": float(s[part].mean()), "rmse": float(np.sqrt(np.mean(e[part] ** 2))),
                        "pixels": int(len(part))})
    return out


def coverage(s: np.ndarray, e: np.ndarray, k: float) -> float:
    """Fraction of pixels whose error is at most ``k`` σ."""
    return float(np.mean(e <= k * s)) if len(s) else float("nan")


def summarize(per_frame: list[dict], pooled: tuple[np.ndarray, np.ndarray]) -> dict:
    rhos = [r["spearman"] for r in per_frame if r["spearman"] is not None]
    return {"spearman_mean": float(np.mean(rhos)) if rhos else None, "frames": len(per_frame),
            "calibration": calibration(*pooled), "within_1sigma": coverage(*pooled, 1.0),
            "within_2sigma": coverage(*pooled, 2.0)}


def plot(rows: dict[str, dict], path: Path, title: str) -> str | None:
    """Calibration curves (RMS error against predicted σ, log-log) of every method with an uncertainty."""
    curves = {n: r["uncertainty"]["calibration"] for n, r in rows.items()
              if r.get("uncertainty") and any(b["std"] > 0 for b in r["uncertainty"]["calibration"])}
    if not curves:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4.2))
    lo, hi = np.inf, 0.0
    for name, bins in curves.items():
        x = [max(b["std"], 1e-6) for b in bins]
        y = [max(b["rmse"], 1e-6) for b in bins]
        lo, hi = min(lo, *x, *y), max(hi, *x, *y)
        rho = rows[name]["uncertainty"]["spearman_mean"]
        ax.plot(x, y, "o-", ms=3, label=f"{name} (Spearman ρ {rho:.2f})" if rho is not None else name)
    ax.plot([lo, hi], [lo, hi], "k--", lw=0.8, label="calibrated")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("predicted σ (std of the samples, HDR)")
    ax.set_ylabel("RMS error against the reference (HDR)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    return Path(path).name
