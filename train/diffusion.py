"""The diffusion process of the denoiser: IF's DDPM with a learned-range variance, as pure functions.

Forward process (Ho et al. 2020), with ᾱ_t the cumulative product of 1 − β_t over the
``squaredcos_cap_v2`` (cosine) schedule of 1000 steps that DeepFloyd IF uses:

    q(z_t | x) = N(√ᾱ_t · x, (1 − ᾱ_t) I)        z_t = √ᾱ_t · x + √(1 − ᾱ_t) · ε

The network predicts 6 channels per pixel: ε̂ (3) and v (3) in [−1, 1], the learned-range
variance of Nichol & Dhariwal 2021 that IF uses: the reverse step's log-variance interpolates
between the posterior's and β_t's,

    log Σ_θ = (v + 1)/2 · log β_t + (1 − (v + 1)/2) · log β̃_t,   β̃_t = (1 − ᾱ_{t−1}) / (1 − ᾱ_t) · β_t

Training loss (IF / improved DDPM "hybrid"): ``‖ε − ε̂‖²`` (mean) plus the variational bound term
``L_t`` in bits per dimension for Σ_θ only (the mean is detached, so the bound trains the
variance and ε-MSE trains the mean):

    L_t = KL( q(z_{t−1} | z_t, x) ‖ p_θ(z_{t−1} | z_t) )           for t > 0
    L_0 = − log p_θ(x | z_1)  (discretised Gaussian, 256 bins)      for t = 0

The sampler is ``diffusers``' ``DDPMScheduler`` configured like IF (``make_scheduler``); this
module uses its ``alphas_cumprod`` and the same variance interpolation, and a test checks that
``log_variance`` agrees with the scheduler's ``_get_variance`` so training and sampling agree.
"""
from __future__ import annotations

import math

import torch

from mcdenoise.pipeline.config import PAPER_STEPS, TRAIN_STEPS  # noqa: F401  (PAPER_STEPS: len(super27()))

# Sampler variance: IF's learned range (the network's second output interpolates log β and log β̃)
# or DDPM's fixed posterior variance β̃ ("small"), which ignores the variance head.
VARIANCES = {"learned": "learned_range", "small": "fixed_small"}


def make_scheduler(threshold_ratio: float = 0.95, sample_max: float = 1.0, variance: str = "learned"):
    """A ``DDPMScheduler`` as DeepFloyd IF stage II uses it (cosine betas, learned range, dynamic
    thresholding); ``variance="small"`` swaps the learned range for the fixed posterior variance."""
    from diffusers import DDPMScheduler

    if variance not in VARIANCES:
        raise ValueError(f"sampler variance must be one of {', '.join(VARIANCES)}, got {variance!r}")
    return DDPMScheduler(num_train_timesteps=TRAIN_STEPS, beta_schedule="squaredcos_cap_v2",
                         variance_type=VARIANCES[variance], prediction_type="epsilon", clip_sample=True,
                         clip_sample_range=1.0, thresholding=True, dynamic_thresholding_ratio=float(threshold_ratio),
                         sample_max_value=float(sample_max))


def super27() -> list[int]:
    """IF's 27-step respacing of the 1000 training steps (``diffusers``' ``super27_timesteps``)."""
    from diffusers.pipelines.deepfloyd_if.timesteps import super27_timesteps

    return list(super27_timesteps)


def _at(a: torch.Tensor, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """a[t] broadcast to ``like``'s shape (B, 1, 1, 1)."""
    return a.to(like.device, torch.float32)[t].view(-1, *([1] * (like.dim() - 1)))


def q_sample(x: torch.Tensor, t: torch.Tensor, noise: torch.Tensor, alphas_cumprod: torch.Tensor) -> torch.Tensor:
    """z_t = √ᾱ_t x + √(1 − ᾱ_t) ε."""
    a = _at(alphas_cumprod, t, x)
    return a.sqrt() * x + (1 - a).sqrt() * noise


def predict_x0(z: torch.Tensor, t: torch.Tensor, eps: torch.Tensor, alphas_cumprod: torch.Tensor) -> torch.Tensor:
    """x̂ = (z_t − √(1 − ᾱ_t) ε̂) / √ᾱ_t, the inverse of ``q_sample`` for a known ε."""
    a = _at(alphas_cumprod, t, z)
    return (z - (1 - a).sqrt() * eps) / a.sqrt()


def posterior(x: torch.Tensor, z: torch.Tensor, t: torch.Tensor, alphas_cumprod: torch.Tensor):
    """Mean and log-variance (clamped at 1e-20, as the scheduler) of q(z_{t−1} | z_t, x) over consecutive steps."""
    a_t = _at(alphas_cumprod, t, x)
    a_prev = torch.where(t > 0, alphas_cumprod.to(x.device, torch.float32)[(t - 1).clamp(min=0)],
                         torch.ones((), device=x.device)).view_as(a_t)
    beta = 1 - a_t / a_prev
    mean = (a_prev.sqrt() * beta / (1 - a_t)) * x + ((1 - beta).sqrt() * (1 - a_prev) / (1 - a_t)) * z
    var = ((1 - a_prev) / (1 - a_t) * beta).clamp(min=1e-20)
    return mean, var.log(), beta


def log_variance(v: torch.Tensor, t: torch.Tensor, alphas_cumprod: torch.Tensor) -> torch.Tensor:
    """log Σ_θ from the model's variance output v ∈ [−1, 1] (learned range, see the module docstring)."""
    a_t = _at(alphas_cumprod, t, v)
    a_prev = torch.where(t > 0, alphas_cumprod.to(v.device, torch.float32)[(t - 1).clamp(min=0)],
                         torch.ones((), device=v.device)).view_as(a_t)
    beta = 1 - a_t / a_prev
    min_log = ((1 - a_prev) / (1 - a_t) * beta).clamp(min=1e-20).log()
    frac = (v + 1) / 2
    return frac * beta.log() + (1 - frac) * min_log


def normal_kl(mean1, logvar1, mean2, logvar2) -> torch.Tensor:
    """KL(N(mean1, e^logvar1) ‖ N(mean2, e^logvar2)) per element, in nats."""
    return 0.5 * (-1.0 + logvar2 - logvar1 + torch.exp(logvar1 - logvar2) + (mean1 - mean2) ** 2 * torch.exp(-logvar2))


def _std_normal_cdf(x: torch.Tensor) -> torch.Tensor:
    return 0.5 * (1.0 + torch.erf(x / math.sqrt(2.0)))


def discretized_gaussian_nll(x: torch.Tensor, mean: torch.Tensor, log_scale: torch.Tensor) -> torch.Tensor:
    """− log P(x) per element, nats, for x in [−1, 1] quantised to 256 bins under N(mean, e^{2·log_scale})."""
    centered = x - mean
    inv = torch.exp(-log_scale)
    cdf_plus = _std_normal_cdf(inv * (centered + 1.0 / 255.0))
    cdf_min = _std_normal_cdf(inv * (centered - 1.0 / 255.0))
    log_cdf_plus = cdf_plus.clamp(min=1e-12).log()
    log_one_minus_cdf_min = (1.0 - cdf_min).clamp(min=1e-12).log()
    log_delta = (cdf_plus - cdf_min).clamp(min=1e-12).log()
    logp = torch.where(x < -0.999, log_cdf_plus, torch.where(x > 0.999, log_one_minus_cdf_min, log_delta))
    return -logp


def vlb_term(x: torch.Tensor, z: torch.Tensor, t: torch.Tensor, eps: torch.Tensor, v: torch.Tensor,
             alphas_cumprod: torch.Tensor) -> torch.Tensor:
    """L_t per sample in bits per dimension (B,), for the model output (ε̂, v) at (z_t, t)."""
    true_mean, true_logvar, _ = posterior(x, z, t, alphas_cumprod)
    x0 = predict_x0(z, t, eps, alphas_cumprod).clamp(-1, 1)
    model_mean, _, _ = posterior(x0, z, t, alphas_cumprod)
    model_logvar = log_variance(v, t, alphas_cumprod)
    kl = normal_kl(true_mean, true_logvar, model_mean, model_logvar).flatten(1).mean(1) / math.log(2.0)
    nll = discretized_gaussian_nll(x, model_mean, 0.5 * model_logvar).flatten(1).mean(1) / math.log(2.0)
    return torch.where(t == 0, nll, kl)


def loss(model_out: torch.Tensor, x: torch.Tensor, z: torch.Tensor, t: torch.Tensor, noise: torch.Tensor,
         alphas_cumprod: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """ε-MSE + L_t (mean over the batch); the bound sees a detached ε̂ so it trains only the variance."""
    eps, v = model_out.float().chunk(2, dim=1)
    mse = ((eps - noise) ** 2).flatten(1).mean(1)
    vb = vlb_term(x, z, t, eps.detach(), v, alphas_cumprod)
    return (mse + vb).mean(), {"mse": mse.mean().detach(), "vb": vb.mean().detach()}


def objective(device: torch.device):
    """The paper's training step: x = GT_clean, x̃ = noisy, t ~ U{0..999}, ε ~ N(0, I),
    z_t = q_sample(x, t, ε), loss = ‖ε − ε̂‖² + L_t(Σ_θ) with ε̂ ⊕ v = model(z_t, x̃, F, t)."""
    acp = make_scheduler().alphas_cumprod.to(device)

    def step(net, batch, gen, device, autocast):
        x, noisy, aux = batch["target"], batch["noisy"], batch.get("aux")
        t = torch.randint(0, TRAIN_STEPS, (x.shape[0],), generator=gen).to(device)
        noise = torch.randn(x.shape, generator=gen).to(device)
        z = q_sample(x, t, noise, acp)
        with torch.autocast(device.type, dtype=autocast, enabled=autocast is not None):
            out = net(z, noisy, aux, t)
        return loss(out, x, z, t, noise, acp)
    return step
