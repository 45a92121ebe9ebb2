"""The loss: each training crop's error relative to the base's (OIDN's) own, where the metrics are read.

    L = w(t) · [ MSE_R(x̂₀, x) / MSE_R(x_est, x) + hdr_weight · L1_PU(x̂₀, x) / L1_PU(x_est, x) ]

R: the x/(1+x) tonemap PSNR is read on; PU: OIDN's HDR space, where highlights keep their relative
error, as HDR-FLIP sees them. Each ratio has a small floor, so crops the base already gets nearly
right do not weigh without bound; dividing by the base's error makes every crop count by its
relative gain, as a mean of per-frame PSNRs does. w(t) is ``formulation.snr_weight``.
"""
from __future__ import annotations

import torch

from mcdenoise.pipeline.metrics import reinhard

from .model import from_pu

FLOOR_R, FLOOR_PU = 1e-7, 1e-5  # floors of the per-crop ratios (MSE on the tonemap, L1 in PU)


def hdr_of(pu: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """HDR radiance of OIDN-space images (B, 3, h, w) at exposures ``scale`` (B,)."""
    return from_pu(pu.clamp(min=0.0)) / scale[:, None, None, None]


def relative_loss(out: torch.Tensor, est: torch.Tensor, target: torch.Tensor, scale: torch.Tensor,
                  hdr_weight: float) -> tuple[torch.Tensor, dict]:
    """Per crop (B,): the tonemapped MSE over OIDN's, plus ``hdr_weight`` × the PU L1 over OIDN's."""
    def mse_r(a):
        return ((reinhard(hdr_of(a, scale)) - reinhard(hdr_of(target, scale))) ** 2).flatten(1).mean(1)

    def l1(a):
        return (a - target).abs().flatten(1).mean(1)

    with torch.no_grad():
        ref_r, ref_pu = mse_r(est) + FLOOR_R, l1(est) + FLOOR_PU
    r, h = mse_r(out) / ref_r, l1(out) / ref_pu
    return r + hdr_weight * h, {"tonemap": r.detach().mean(), "pu": h.detach().mean()}
