"""Training losses of the cleaner, the Isik baseline and AFGSA.

The image metrics live in ``pipeline.metrics`` (one definition for training and evaluation); this
module names the ones the trainers use and adds AFGSA's adversarial terms.

AFGSA (Yu et al. 2021) trains its generator G with L1 in log1p space plus a WGAN-GP adversarial
term (the authors' code: weight 5e-3, gradient penalty 10), the critic D with the WGAN-GP loss:

    L_D = E[D(G(x))] − E[D(y)] + λ_gp E[(‖∇D(x̂)‖₂ − 1)²],   x̂ = α y + (1 − α) G(x), α ~ U(0, 1)
    L_G = ‖G(x) − y‖₁ + w_adv (−E[D(G(x))])

with y the target in log1p space. w_adv = 0 is the L1-only ablation: the critic is not used.
"""
from __future__ import annotations

import torch

from mcdenoise.pipeline.metrics import SMAPE_EPS, l1, smape

__all__ = ["smape", "l1", "SMAPE_EPS", "log_radiance", "critic_loss", "generator_loss"]


def log_radiance(hdr: torch.Tensor) -> torch.Tensor:
    """HDR radiance → the log1p space AFGSA predicts and is trained in (negatives clamped to 0)."""
    return torch.log1p(hdr.clamp(min=0.0))


def gradient_penalty(critic, real: torch.Tensor, fake: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """E[(‖∇D(x̂)‖₂ − 1)²] at random points x̂ between real and fake (one α per crop)."""
    alpha = torch.rand(real.shape[0], 1, 1, 1, generator=generator).to(real)
    mixed = (alpha * real + (1 - alpha) * fake).requires_grad_(True)
    grad, = torch.autograd.grad(critic(mixed).sum(), mixed, create_graph=True)
    return ((grad.flatten(1).norm(dim=1) - 1.0) ** 2).mean()


def critic_loss(critic, real: torch.Tensor, fake: torch.Tensor, gp_weight: float,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """WGAN-GP loss of the critic (``fake`` is detached here); terms: the Wasserstein estimate
    E[D(y)] − E[D(G(x))] and the penalty."""
    fake = fake.detach()
    wasserstein = critic(real).mean() - critic(fake).mean()
    gp = gradient_penalty(critic, real, fake, generator)
    loss = -wasserstein + gp_weight * gp
    return loss, {"wasserstein": float(wasserstein.detach()), "gp": float(gp.detach())}


def generator_loss(fake: torch.Tensor, real: torch.Tensor, critic, adv_weight: float
                   ) -> tuple[torch.Tensor, dict[str, float]]:
    """L1 (log space) + adv_weight · (−E[D(fake)]); with adv_weight 0 the critic is never called."""
    rec = (fake - real).abs().mean()
    if adv_weight == 0:
        return rec, {"l1": float(rec.detach())}
    adv = -critic(fake).mean()
    return rec + adv_weight * adv, {"l1": float(rec.detach()), "adv": float(adv.detach())}
