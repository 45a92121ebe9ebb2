"""Inference: IF's DDPM sampler over the ``super27`` steps, started from the q-sampled noisy render.

    z_{t_s} = √ᾱ · x̃ + √(1 − ᾱ) · ε        (x̃: the noisy render in model space, t_s = super27[skip])
    for t in super27[skip:]:  z ← DDPMScheduler.step(model(z, x̃, F, t), t, z)

With ``skip = 0`` the start is t = 999, where ᾱ ≈ 0: pure noise, the paper's Table 1 setting. A
larger ``skip`` starts from the noisy render itself, noised just enough to cover its Monte Carlo
noise (paper Fig. 4: up to 18 of 27 steps can go). Dynamic thresholding of the predicted clean
image (IF's, ``threshold_ratio``) keeps every step inside [−1, 1]. Everything random comes from
one ``torch.Generator`` seeded with ``seed``: the same inputs and seed give the same output.

``sample_tiled`` bounds memory for large frames: overlapping tiles (sides a multiple of the
base's down-sampling factor), each sampled on its own with a seed derived from its position, and
blended with linear ramps across the overlap.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from .diffusion import make_scheduler, super27


def _pad(x: torch.Tensor, multiple: int) -> tuple[torch.Tensor, tuple[int, int]]:
    H, W = x.shape[-2:]
    ph, pw = (-H) % multiple, (-W) % multiple
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    return x, (H, W)


@torch.no_grad()
def sample(model, noisy: torch.Tensor, aux: torch.Tensor | None, skip: int = 0, seed: int = 0,
           threshold_ratio: float = 0.95, autocast_dtype: torch.dtype | None = None,
           variance: str = "learned") -> torch.Tensor:
    """The denoised image in model space, (B, 3, H, W) like ``noisy``; any H, W (padded internally).

    ``variance``: "learned" (IF: the network's variance output) or "small" (the posterior
    variance β̃ whatever the network says; see ``diffusion.VARIANCES``)."""
    if not 0 <= skip < 27:
        raise ValueError(f"skip must be in [0, 26], got {skip}")
    device = noisy.device
    m = getattr(model, "multiple", 1)
    noisy_p, (H, W) = _pad(noisy.float(), m)
    aux_p = _pad(aux.float(), m)[0] if aux is not None else None
    sched = make_scheduler(threshold_ratio, variance=variance)
    channels = noisy_p.shape[1] if variance == "small" else None   # fixed variance: the scheduler wants ε only
    sched.set_timesteps(timesteps=super27())
    steps = sched.timesteps[skip:]
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    noise = torch.randn(noisy_p.shape, generator=gen).to(device)
    z = sched.add_noise(noisy_p, noise, steps[:1])
    for t in steps:
        tt = t.to(device).expand(noisy_p.shape[0])
        with torch.autocast(device.type, dtype=autocast_dtype, enabled=autocast_dtype is not None):
            out = model(z, noisy_p, aux_p, tt)
        z = sched.step(out[:, :channels].float(), t, z, generator=gen).prev_sample   # noise drawn on the CPU generator
    return z[..., :H, :W].clamp(-1, 1)


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
def sample_tiled(model, noisy: torch.Tensor, aux: torch.Tensor | None, tile: int = 256, overlap: int = 32,
                 **kw) -> torch.Tensor:
    """``sample`` in overlapping tiles for a (1, 3, H, W) frame; memory bounded by the tile size."""
    H, W = noisy.shape[-2:]
    if H <= tile and W <= tile:
        return sample(model, noisy, aux, **kw)
    seed = int(kw.pop("seed", 0))
    out = torch.zeros(noisy.shape[0], 3, H, W)
    weight = torch.zeros(1, 1, H, W)
    ys, xs = tiles(H, tile, overlap), tiles(W, tile, overlap)
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            h, w = min(tile, H), min(tile, W)
            sl = (..., slice(y, y + h), slice(x, x + w))
            a = aux[sl] if aux is not None else None
            res = sample(model, noisy[sl], a, seed=seed * 1_000_003 + i * 1009 + j, **kw).cpu()
            wy = _ramp(h, overlap, y > 0, y + h < H)
            wx = _ramp(w, overlap, x > 0, x + w < W)
            wt = torch.from_numpy(np.outer(wy, wx))[None, None]
            out[sl] += res * wt
            weight[sl] += wt
    return (out / weight).to(noisy.device)
