"""Inference: the reverse diffusion of either formulation (``train.formulation``), from ``diffusers``' schedulers.

**paper** (ε, IF's cosine schedule): IF's DDPM over the ``super27`` steps, started from the
q-sampled noisy render (paper Fig. 4):

    z_{t_s} = √ᾱ · x̃ + √(1 − ᾱ) · ε        (x̃: the noisy render in model space, t_s = super27[skip])
    for t in super27[skip:]:  z ← DDPMScheduler.step(model(z, x̃, F, t), t, z)

With ``skip = 0`` the start is t = 999, where ᾱ ≈ 0: pure noise, the paper's Table 1 setting.
Dynamic thresholding of the predicted clean image (IF's, ``threshold_ratio``) keeps every step in
[−1, 1]; ``variance`` is IF's learned range or the fixed posterior variance ("small").

**refine** (v or x₀ prediction, usually zero terminal SNR): DDIM (deterministic) or DDPM over
``steps`` trailing timesteps of which the first ``skip`` are not run; the diffused signal y is
the scaled residual around the image input (the first estimate) or the image itself:

    z_{t_s} = √ᾱ · y_start + √(1 − ᾱ) · ε,   y_start = 0 / (x̃ − x_est)/s / pure ε
                                              for start = estimate / render / noise
    for t in timesteps[skip:]:  z ← scheduler.step(model(z, x_est, F, t), t, z)
    x = x_est + s · z

With a zero terminal SNR and ``steps = 1`` the single step from T returns the network's x̂₀.
Everything random comes from one ``torch.Generator`` seeded with ``seed``: the same inputs and
seed give the same output. ``samples = K`` draws K samples (seeds seed … seed + K − 1) and returns
their mean and per-pixel standard deviation (the denoiser's uncertainty).

``sample_tiled`` bounds memory for large frames: overlapping tiles (sides a multiple of the
base's down-sampling factor), each sampled on its own with a seed derived from its position, and
blended with linear ramps across the overlap.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from .diffusion import PAPER_STEPS, make_scheduler, super27
from .formulation import Formulation

PAPER = Formulation(prediction="epsilon", schedule="if", estimate="none", residual=False, steps=PAPER_STEPS,
                    start="render")


def _pad(x: torch.Tensor, multiple: int) -> tuple[torch.Tensor, tuple[int, int]]:
    H, W = x.shape[-2:]
    ph, pw = (-H) % multiple, (-W) % multiple
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    return x, (H, W)


@torch.no_grad()
def sample(model, noisy: torch.Tensor, aux: torch.Tensor | None, image: torch.Tensor | None = None,
           formulation: Formulation = PAPER, steps: int | None = None, skip: int | None = None,
           start: str | None = None, seed: int = 0, threshold_ratio: float = 0.95,
           autocast_dtype: torch.dtype | None = None, variance: str = "learned", sampler: str | None = None
           ) -> torch.Tensor:
    """The denoised image in model space, (B, 3, H, W) like ``noisy``; any H, W (padded internally).

    ``image``: the first estimate in model space (the refine formulation; default: ``noisy``).
    ``steps``, ``skip``, ``start``, ``sampler`` default to the formulation's."""
    f = formulation
    skip = f.skip if skip is None else int(skip)
    m = getattr(model, "multiple", 1)
    noisy_p, (H, W) = _pad(noisy.float(), m)
    image_p = _pad(image.float(), m)[0] if image is not None else noisy_p
    aux_p = _pad(aux.float(), m)[0] if aux is not None else None
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    if f.paper:
        z = _paper(model, noisy_p, aux_p, skip, gen, threshold_ratio, autocast_dtype, variance)
    else:
        z = _refine(model, noisy_p, image_p, aux_p, f, f.steps if steps is None else int(steps), skip,
                    start or f.start, sampler or f.sampler, gen, autocast_dtype)
    return z[..., :H, :W].clamp(-1, 1)


def _model(model, z, image, aux, t, autocast_dtype):
    tt = t.to(z.device).expand(z.shape[0])
    with torch.autocast(z.device.type, dtype=autocast_dtype, enabled=autocast_dtype is not None):
        return model(z, image, aux, tt)


def _paper(model, noisy, aux, skip, gen, threshold_ratio, autocast_dtype, variance) -> torch.Tensor:
    if not 0 <= skip < PAPER_STEPS:
        raise ValueError(f"skip must be in [0, {PAPER_STEPS - 1}], got {skip}")
    sched = make_scheduler(threshold_ratio, variance=variance)
    channels = noisy.shape[1] if variance == "small" else None   # fixed variance: the scheduler wants ε only
    sched.set_timesteps(timesteps=super27())
    steps = sched.timesteps[skip:]
    noise = torch.randn(noisy.shape, generator=gen).to(noisy.device)
    z = sched.add_noise(noisy, noise, steps[:1])
    for t in steps:
        out = _model(model, z, noisy, aux, t, autocast_dtype)
        z = sched.step(out[:, :channels].float(), t, z, generator=gen).prev_sample   # noise drawn on the CPU generator
    return z


def _refine(model, noisy, image, aux, f: Formulation, steps: int, skip: int, start: str, sampler: str, gen,
            autocast_dtype) -> torch.Tensor:
    if not 1 <= steps <= 1000 or not 0 <= skip < steps:
        raise ValueError(f"need 1 <= steps <= 1000 and 0 <= skip < steps, got steps={steps}, skip={skip}")
    if start == "noise" and skip:
        raise ValueError("start=noise begins at t = T: it cannot skip steps (use start=estimate or render)")
    sched = f.scheduler(sampler)
    sched.set_timesteps(steps)
    timesteps = sched.timesteps[skip:]
    C = image.shape[1]
    noise = torch.randn(image.shape, generator=gen).to(image.device)
    if start == "noise":
        z = noise
    else:
        y = f.target(noisy, image) if start == "render" else f.target(image, image)
        z = sched.add_noise(y, noise, timesteps[:1])
    for t in timesteps:
        out = _model(model, z, image, aux, t, autocast_dtype)
        z = sched.step(out[:, :C].float(), t, z, generator=gen).prev_sample
    return f.image_of(z, image)


@torch.no_grad()
def sample_many(model, noisy, aux, samples: int = 1, seed: int = 0, **kw) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean, per-pixel standard deviation) over ``samples`` samples with seeds seed, seed + 1, …;
    the standard deviation is 0 for one sample (and for a deterministic sampler)."""
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    outs = torch.stack([sample(model, noisy, aux, seed=seed + k, **kw) for k in range(samples)])
    return outs.mean(0), outs.std(0, unbiased=False)


def _ramp(n: int, overlap: int, start: bool, end: bool) -> np.ndarray:
    w = np.ones(n, np.float32)
    if overlap > 0:
        r = (np.arange(overlap, dtype=np.float32) + 0.5) / overlap
        if start:
            w[:overlap] = r
        if end:
            w[n - overlap:] = r[::-1]
    return w


def tiles(size: int, tile: int, overlap: int) -> list[int]:
    """Start offsets of tiles of side ``tile`` covering [0, size) with at least ``overlap`` shared."""
    if size <= tile:
        return [0]
    step = tile - overlap
    starts = list(range(0, size - tile, step)) + [size - tile]
    return sorted(set(starts))


@torch.no_grad()
def sample_tiled(model, noisy: torch.Tensor, aux: torch.Tensor | None, image: torch.Tensor | None = None,
                 tile: int = 256, overlap: int = 32, samples: int = 1, **kw) -> tuple[torch.Tensor, torch.Tensor]:
    """``sample_many`` in overlapping tiles for a (1, 3, H, W) frame: (mean, std); memory bounded by the tile."""
    H, W = noisy.shape[-2:]
    if H <= tile and W <= tile:
        return sample_many(model, noisy, aux, samples=samples, image=image, **kw)
    seed = int(kw.pop("seed", 0))
    mean = torch.zeros(noisy.shape[0], 3, H, W)
    std = torch.zeros_like(mean)
    weight = torch.zeros(1, 1, H, W)
    ys, xs = tiles(H, tile, overlap), tiles(W, tile, overlap)
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            h, w = min(tile, H), min(tile, W)
            sl = (..., slice(y, y + h), slice(x, x + w))
            part = [t[sl] if t is not None else None for t in (noisy, aux, image)]
            m, s = sample_many(model, part[0], part[1], samples=samples, image=part[2],
                               seed=seed * 1_000_003 + i * 1009 + j, **kw)
            wt = torch.from_numpy(np.outer(_ramp(h, overlap, y > 0, y + h < H), _ramp(w, overlap, x > 0, x + w < W)))
            mean[sl] += m.cpu() * wt
            std[sl] += s.cpu() * wt
            weight[sl] += wt
    return (mean / weight).to(noisy.device), (std / weight).to(noisy.device)
