"""The diffusion: what is diffused and predicted (``Formulation``), its schedule, the timesteps training
draws, the min-SNR weight, and the sampler (the reverse diffusion around the base's output, and the
strength knob).

What the diffusion model diffuses and predicts, its schedule, and how training draws timesteps.

The model refines the base's output x_est (OIDN's own, in OIDN's output space, PU of the exposed
radiance). It diffuses the scaled residual

    y = (x − x_est) / s          s = ``residual_scale``

and predicts x̂₀ (``prediction: sample``): a Control Module whose zero convolutions are still zero
predicts x̂₀ = x_est at every step, so every sampler returns the base's output exactly and training
starts from OIDN. The schedule is IF's cosine one, rescaled to zero terminal SNR with trailing
timesteps (``schedule: zero_snr``; Lin et al. 2023), so one DDIM step from t = T is the network's
direct estimate; more steps and several samples are there for the uncertainty. Training t is drawn
with probability ``t_focus`` from the timesteps a sampler with one of the ``train_steps`` step counts
visits (each count equally likely), else uniformly; the loss (``train.loss``) is weighted by min-SNR-γ
(Hang et al. 2023) in x₀-error terms, floored, because min(SNR, γ) is 0 at SNR = 0, exactly the step
whose output is the one-step estimate:

    w(t) = max(min(SNR_t, γ), floor)

``prediction``, ``estimate``, ``residual``, ``sampler`` and ``loss_norm`` are fixed (x₀ of the residual
around OIDN's output, DDIM, the per-crop loss); they are fields so that a model.json records them.

The sampler: The diffused signal is the residual y = (x − x_est) / residual_scale around the base's output x_est;
the network predicts x̂₀, and with the ``zero_snr`` schedule one DDIM step from t = T is its direct
estimate; more steps and several samples give the uncertainty (``train.infer``).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from mcdenoise.pipeline.config import TRAIN_STEPS, ConfigError, check_formulation

from .model import ControlledOIDN

# The diffusion.* keys a Formulation is built from (the rest are fixed, see the module docstring)
CONFIG_KEYS = ("schedule", "residual_scale", "snr_gamma", "snr_floor", "t_focus", "steps", "start", "skip")
FIXED = {"prediction": "sample", "estimate": "oidn", "residual": True, "sampler": "ddim"}


class FormulationError(ConfigError):
    """A combination of ``diffusion.*`` keys that cannot work; the message names the keys."""


@dataclass(frozen=True)
class Formulation:
    prediction: str = "sample"
    schedule: str = "zero_snr"
    estimate: str = "oidn"
    residual: bool = True
    residual_scale: float = 0.02
    snr_gamma: float = 5.0
    snr_floor: float = 1.0
    t_focus: float = 0.9
    sampler: str = "ddim"
    steps: int = 1
    start: str = "estimate"
    skip: int = 0
    loss_norm: str = "crop"

    def __post_init__(self):
        check(self)

    def record(self) -> dict:
        """The fields, for model.json and the resume fingerprint. ``loss_norm: none`` is left out: it is
        what models made before the per-crop loss recorded."""
        r = asdict(self)
        if r["loss_norm"] == "none":
            del r["loss_norm"]
        return r

    @classmethod
    def from_config(cls, d) -> "Formulation":
        """From the ``diffusion`` config section (``pipeline.config.DiffusionConfig``)."""
        return cls(**{k: getattr(d, k) for k in CONFIG_KEYS})

    @classmethod
    def from_record(cls, record: dict) -> "Formulation":
        """From ``record()``; a record without ``loss_norm`` is from before the key (``none``)."""
        known = set(cls.__dataclass_fields__)
        return cls(**{"loss_norm": "none", **{k: v for k, v in record.items() if k in known}})

    # ---- schedules ---------------------------------------------------------------------------

    def scheduler(self, sampler: str | None = None):
        """The ``diffusers`` scheduler of this formulation (DDIM, or DDPM for training's ``add_noise``;
        trailing timesteps)."""
        from diffusers import DDIMScheduler, DDPMScheduler

        kind = sampler or self.sampler
        common = dict(num_train_timesteps=TRAIN_STEPS, beta_schedule="squaredcos_cap_v2",
                      prediction_type="sample", clip_sample=False,
                      rescale_betas_zero_snr=self.schedule == "zero_snr", timestep_spacing="trailing")
        if kind == "ddim":
            return DDIMScheduler(set_alpha_to_one=True, **common)
        return DDPMScheduler(variance_type="fixed_small", **common)

    def train_timesteps(self, steps: list[int]) -> list[torch.Tensor]:
        """Per step count in ``steps``, the timesteps a sampler with that many steps visits (trailing spacing)."""
        sched = self.scheduler("ddim")
        out = []
        for n in steps:
            sched.set_timesteps(int(n))
            out.append(sched.timesteps.clone())
        return out

    def draw_t(self, n: int, focus: list[torch.Tensor], gen: torch.Generator) -> torch.Tensor:
        """n training timesteps: with probability ``t_focus`` a step count of ``focus`` at random, then one of
        its timesteps at random (so the one step of a 1-step sampler is drawn as often as all 27 of
        a 27-step one together); else uniform over 0..999."""
        uniform = torch.randint(0, TRAIN_STEPS, (n,), generator=gen)
        which = torch.randint(0, len(focus), (n,), generator=gen)
        pos = torch.rand(n, generator=gen)
        picked = torch.stack([focus[int(w)][min(int(p * len(focus[int(w)])), len(focus[int(w)]) - 1)]
                              for w, p in zip(which, pos)])
        use = torch.rand(n, generator=gen) < self.t_focus
        return torch.where(use, picked, uniform)


def snr_weight(sched, t: torch.Tensor, gamma: float, floor: float) -> torch.Tensor:
    """Per-sample loss weight: min-SNR-γ in x₀-error terms, floored (see the module docstring)."""
    from diffusers.training_utils import compute_snr

    snr = compute_snr(sched, t.cpu()).float()
    return torch.clamp(torch.minimum(snr, torch.full_like(snr, gamma)), min=floor)


def check(f: Formulation) -> None:
    """Refuse combinations that cannot work (``pipeline.config.check_formulation``, the rules the config's
    diffusion section is loaded with), naming the ``diffusion.*`` key."""
    def bad(key: str, msg: str):
        raise FormulationError(f"diffusion.{key}: {msg}")
    for key, value in FIXED.items():
        if getattr(f, key) != value:
            bad(key, f"{getattr(f, key)!r}: this denoiser is {value!r} (x0 prediction of the residual around OIDN's "
                     "output, sampled with DDIM)")
    if f.loss_norm not in ("none", "crop"):
        bad("loss_norm", f"expected 'crop' or 'none', got {f.loss_norm!r}")
    check_formulation(f, bad)


# ---- the sampler ----------------------------------------------------------------------------------


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
