"""What the diffusion model diffuses and predicts, and how its loss is weighted (``diffusion.*`` keys).

Two formulations share the model, the data and the training loop:

- ``paper`` (``prediction: epsilon``, ``schedule: if``): DeepFloyd IF stage II as the paper uses it:
  ε-prediction with a learned-range variance over IF's cosine schedule, the hybrid loss
  ε-MSE + L_t (``train.diffusion``), sampled with IF's DDPM over the ``super27`` steps. What real
  IF-II-M weights need, kept unchanged.
- ``refine`` (any other combination; the default): a diffusion model that refines a first estimate
  x_est of the clean image (``diffusion.estimate``: OIDN, or none: the noisy render itself). With
  ``residual: true`` it diffuses the scaled residual

      r = (x − x_est) / s          (model space, s = ``residual_scale``)

  and the estimate is the base's image input (where IF-II reads its low-resolution image), so the
  Control Module still sees the noisy render among its buffers. The schedule is IF's cosine one,
  rescaled to zero terminal SNR with trailing timesteps (``schedule: zero_snr``; Lin et al. 2023),
  so one step from t = T is the network's direct estimate of r. The network predicts
  ``prediction`` ∈ {v, sample, epsilon} (Salimans & Ho 2022; ε is refused with a zero terminal
  SNR, where it says nothing about x); the loss is the MSE against ``DDPMScheduler``'s targets
  (``get_velocity`` for v), weighted by min-SNR-γ (Hang et al. 2023) expressed in x₀-error terms
  and floored, because min(SNR, γ) is 0 at SNR = 0, exactly the step whose output is the one-step
  estimate:

      w_x0(t) = max(min(SNR_t, γ), floor);   w = w_x0 / SNR (ε), w_x0 / (SNR + 1) (v), w_x0 (sample)

  With ``prediction: sample`` an untrained network whose last layer is zero predicts r̂ = 0 at every
  step, so every sampler returns the estimate exactly: training starts from the estimate.
  Training t is drawn with probability ``t_focus`` from the timesteps a sampler with one of the
  ``train_steps`` step counts visits (each count equally likely), else uniformly.

  ``loss_norm: crop`` (the default) divides each crop's loss by the error of its own first estimate (the model-
  space MSE of x_est against x, in the diffused signal's units, plus a floor ``NORM_FLOOR``):

      L = w(t) · MSE(pred, target) / (MSE(x_est, x) + floor)

  At t = T with x₀-prediction that is the crop's error relative to the estimate's, so each crop
  counts by how many dB the network gains or loses on it, as the evaluation's mean of per-frame
  PSNRs does. With the plain MSE (``none``) the few hard crops, whose errors are 10-100× larger,
  dominate the gradient: measured on the shipped model's validation frames, the network then holds
  the hard frames level and loses 0.1-0.4 dB on the easy ones (docs/diffusion.md). The paper
  formulation keeps IF's hybrid loss (``train.diffusion``), which ``loss_norm`` does not change.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from mcdenoise.pipeline.config import TRAIN_STEPS, ConfigError, check_formulation, is_paper

# diffusers' prediction_type of each diffusion.prediction (pipeline.config.PREDICTIONS)
PREDICTION_TYPES = {"epsilon": "epsilon", "v": "v_prediction", "sample": "sample"}
# Floor of the per-crop normaliser, in model-space MSE: about 60 dB in the log space, so the crops
# that are already near perfect (flat emitters, black background) weigh at most ~1000 times an
# average one instead of without bound.
NORM_FLOOR = 1e-6


class FormulationError(ConfigError):
    """A combination of ``diffusion.*`` keys that cannot work; the message names the keys."""


@dataclass(frozen=True)
class Formulation:
    prediction: str = "sample"
    schedule: str = "zero_snr"
    estimate: str = "oidn+isik"
    residual: bool = True
    residual_scale: float = 0.05
    snr_gamma: float = 5.0
    snr_floor: float = 1.0
    t_focus: float = 0.8
    sampler: str = "ddim"
    steps: int = 1
    start: str = "estimate"
    skip: int = 0
    loss_norm: str = "crop"

    def __post_init__(self):
        check(self)

    @property
    def paper(self) -> bool:
        """IF's own path: ε, learned-range variance, hybrid loss, super27 DDPM."""
        return is_paper(self)

    def record(self) -> dict:
        """The fields, for model.json and the resume fingerprint. ``loss_norm: none`` is left out: it is
        what every run and model made before the key trained with, so they keep their fingerprint and
        resume with ``diffusion.loss_norm=none``."""
        r = asdict(self)
        if r["loss_norm"] == "none":
            del r["loss_norm"]
        return r

    @classmethod
    def from_config(cls, d) -> "Formulation":
        """From the ``diffusion`` config section (``pipeline.config.DiffusionConfig``)."""
        return cls(**{k: getattr(d, k) for k in cls.__dataclass_fields__})

    @classmethod
    def from_record(cls, record: dict) -> "Formulation":
        """From ``record()``; a record without ``loss_norm`` is from before the key (``none``)."""
        known = set(cls.__dataclass_fields__)
        return cls(**{"loss_norm": "none", **{k: v for k, v in record.items() if k in known}})

    # ---- what is diffused --------------------------------------------------------------------

    def target(self, x: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """The diffused signal: the scaled residual around ``image`` (the estimate) or x itself."""
        return (x - image) / self.residual_scale if self.residual else x

    def image_of(self, target: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """Inverse of ``target``: model-space image from the diffused signal."""
        return image + self.residual_scale * target if self.residual else target

    # ---- schedules ---------------------------------------------------------------------------

    def scheduler(self, sampler: str | None = None):
        """The ``diffusers`` scheduler of this formulation (DDIM or DDPM; trailing timesteps)."""
        from diffusers import DDIMScheduler, DDPMScheduler

        kind = sampler or self.sampler
        common = dict(num_train_timesteps=TRAIN_STEPS, beta_schedule="squaredcos_cap_v2",
                      prediction_type=PREDICTION_TYPES[self.prediction], clip_sample=False,
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

    def objective(self, focus_steps: list[int]):
        """The refine formulation's training step (``train.train.ControlTask``'s ``objective``): y = target(x, x_est),
        t from ``draw_t``, z_t = add_noise(y, ε, t), weighted loss of model(z_t, x_est, F, t)."""
        sched = self.scheduler("ddpm")
        focus = self.train_timesteps(focus_steps)

        def step(net, batch, gen, device, autocast):
            image = batch.get("image", batch["noisy"])
            y = self.target(batch["target"], image)
            t = self.draw_t(y.shape[0], focus, gen)
            noise = torch.randn(y.shape, generator=gen).to(device)
            z = sched.add_noise(y, noise, t.to(device))
            with torch.autocast(device.type, dtype=autocast, enabled=autocast is not None):
                out = net(z, image, batch.get("aux"), t.to(device))
            return self.loss(out, y, z, t.to(device), noise, sched, norm=self.crop_norm(y, image))
        return step

    def crop_norm(self, y: torch.Tensor, image: torch.Tensor) -> torch.Tensor | None:
        """Per crop, the first estimate's error in the diffused signal's units plus the floor (``loss_norm:
        crop``), or None. ``target(image, image)`` is where the estimate itself sits in that signal."""
        if self.loss_norm == "none":
            return None
        unit = self.residual_scale ** 2 if self.residual else 1.0
        own = ((y - self.target(image, image)) ** 2).flatten(1).mean(1)
        return own.detach().float() + NORM_FLOOR / unit

    # ---- loss --------------------------------------------------------------------------------

    def loss(self, model_out: torch.Tensor, x0: torch.Tensor, z: torch.Tensor, t: torch.Tensor,
             noise: torch.Tensor, sched, norm: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Weighted MSE of the prediction (first channels of ``model_out``) against its target, each
        sample's divided by ``norm`` when given (``crop_norm``)."""
        pred = model_out[:, :x0.shape[1]].float()
        if self.prediction == "epsilon":
            target = noise
        elif self.prediction == "v":
            target = sched.get_velocity(x0, noise, t)
        else:
            target = x0
        w = snr_weight(sched, t, self.prediction, self.snr_gamma, self.snr_floor).to(pred.device)
        mse = ((pred - target) ** 2).flatten(1).mean(1)
        if norm is not None:
            w = w / norm.to(pred.device)
        return (w * mse).mean(), {"mse": mse.mean().detach(), "vb": torch.zeros((), device=pred.device)}


def snr_weight(sched, t: torch.Tensor, prediction: str, gamma: float, floor: float) -> torch.Tensor:
    """Per-sample loss weight: min-SNR-γ in x₀-error terms, floored, converted to the prediction's
    error (see the module docstring)."""
    from diffusers.training_utils import compute_snr

    snr = compute_snr(sched, t.cpu()).float()
    w0 = torch.clamp(torch.minimum(snr, torch.full_like(snr, gamma)), min=floor)
    if prediction == "epsilon":
        return w0 / snr
    if prediction == "v":
        return w0 / (snr + 1.0)
    return w0


def check(f: Formulation) -> None:
    """Refuse combinations that cannot work (``pipeline.config.check_formulation``, the rules the config's
    diffusion section is loaded with), naming the ``diffusion.*`` key."""
    def bad(key: str, msg: str):
        raise FormulationError(f"diffusion.{key}: {msg}")
    check_formulation(f, bad)
