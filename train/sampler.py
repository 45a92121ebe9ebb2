"""The sampler: the reverse diffusion around the base's output in OIDN's space, and the strength knob.

The diffused signal is the residual y = (x − x_est) / residual_scale around the base's output x_est;
the network predicts x̂₀, and with the ``zero_snr`` schedule one DDIM step from t = T is its direct
estimate; more steps and several samples give the uncertainty (``train.infer``).
"""
from __future__ import annotations

import torch

from mcdenoise.pipeline.config import ConfigError

from .formulation import Formulation
from .model import ControlledOIDN


@torch.no_grad()
def sample(model: ControlledOIDN, x: torch.Tensor, cond: torch.Tensor, f: Formulation, steps: int | None = None,
           skip: int | None = None, start: str | None = None, seed: int = 0, samples: int = 1
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(mean, per-pixel std, x_est) in OIDN's space for inputs padded to a multiple of 16: ``samples``
    DDIM runs (seeds seed, seed + 1, …) of ``steps`` trailing steps, the first ``skip`` not run,
    starting from pure noise (``noise``) or the q-sampled estimate (``estimate``) or render (``render``)."""
    steps, skip, start = f.steps if steps is None else int(steps), f.skip if skip is None else int(skip), start or f.start
    if not 1 <= steps <= 1000 or not 0 <= skip < steps or (start == "noise" and skip):
        raise ValueError(f"need 1 <= steps <= 1000, 0 <= skip < steps (0 from noise), got {steps}, {skip}, {start}")
    base = model.estimate(x)
    est = base[1]
    sched = f.scheduler("ddim")
    sched.set_timesteps(steps)
    ts = sched.timesteps[skip:]
    s = f.residual_scale
    outs = []
    for k in range(samples):
        gen = torch.Generator().manual_seed(int(seed) + k)
        noise = torch.randn(est.shape, generator=gen).to(est.device)
        y = (x[:, :3] - est) / s if start == "render" else torch.zeros_like(est)
        z = noise if start == "noise" else sched.add_noise(y, noise, ts[:1])
        for t in ts:
            out, _ = model(x, cond, z, t.expand(x.shape[0]).to(x.device), base=base)
            z = sched.step((out - est) / s, t, z).prev_sample
        outs.append(est + s * z)
    outs = torch.stack(outs)
    return outs.mean(0), outs.std(0, unbiased=False), est


def with_strength(mean: torch.Tensor, std: torch.Tensor, est: torch.Tensor, strength: float
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """The base's output ``est`` plus ``strength`` times what the Control Module changed (``mean - est``),
    and the samples' spread scaled alike: ControlNet's conditioning scale, read in OIDN's output space,
    where a frozen base keeps what it knew. 1 is the trained model, 0 the base alone; in between trades
    the gain on data like the training set for less change on data unlike it."""
    if strength == 1.0:
        return mean, std
    return est + strength * (mean - est), strength * std


def check_strength(value, what: str) -> float:
    """``value`` as a strength in [0, 1], else a ConfigError that names ``what``."""
    try:
        k = float(value)
    except (TypeError, ValueError):
        k = float("nan")
    if not 0.0 <= k <= 1.0:
        raise ConfigError(f"{what}: {value!r}: expected a number from 0 (the base alone) to 1 (the trained model)")
    return k
