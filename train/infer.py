"""Denoise a frame with a trained run: the evaluator's and ``python -m pipeline denoise``'s entry point.

    den = load_denoiser(run_dir(cfg, 4))                 # or base_only=True: the ablation row
    hdr = den.denoise(store.read(scene, frame, 4), spp=4, seed=0)          # (H, W, 3) float32
    hdr, std = den.denoise(buffers, spp=4, samples=8, with_std=True)       # mean of 8 and their std

``buffers`` are what ``Store.read`` returns (HxWxC arrays by buffer name, variances included);
missing feature buffers count as their background value. Non-finite input values are replaced
by 0 and counted in ``den.last_repaired`` (never passed to the network). Frames larger than
``diffusion.tile`` are denoised in overlapping tiles, so memory is bounded at any size.

What the model cannot represent is said, not hidden:

- the model space holds radiance in [0, 6] (as the paper); with a first estimate (the refine
  formulation) a pixel whose estimate is above 6 keeps the estimate's value, without one the
  output is clamped at 6. ``den.last_clamped`` counts such pixels;
- a frame whose noisy radiance is exactly 0 everywhere carried no light at all: it is returned
  black (``den.last_black``), never an invented image;
- an input without the renderer's variance, albedo and normal (``train.estimate.RENDERER_BUFFERS``,
  e.g. an EXR with only R, G, B) is not what the network was trained on: the refine formulation
  returns its first estimate, OIDN with whatever albedo and normal there are
  (``den.last_estimate_only``).
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

from mcdenoise.pipeline.config import ConfigError
from mcdenoise.pipeline.numerics import repair_nonfinite
from mcdenoise.pipeline.runs import pick_device

from .data import CLAMP, from_model, model_inputs, to_planar
from .estimate import Estimator, has_renderer_buffers
from .model import formulation, load, load_run_estimator, run_dir
from .sampler import sample_tiled
from .train import autocast_dtype

__all__ = ["Denoiser", "load_denoiser", "run_dir"]


def hdr_std(mean_model: np.ndarray, std_model: np.ndarray, tonemap: str) -> np.ndarray:
    """A model-space standard deviation in HDR units: times the local slope of ``from_model``."""
    h = 1e-3
    slope = (from_model(torch.from_numpy(mean_model + h), tonemap) -
             from_model(torch.from_numpy(mean_model - h), tonemap)).numpy() / (2 * h)
    return np.abs(slope) * std_model


class Denoiser:
    def __init__(self, model, meta: dict, device: torch.device, tile: int = 256, overlap: int = 32,
                 precision: str = "auto", estimator: Estimator | None = None):
        self.model, self.meta, self.device = model, meta, device
        self.formulation = formulation(meta)
        self.estimator = estimator or Estimator(self.formulation.estimate)
        self.tile, self.overlap = int(tile), int(overlap)
        self.autocast = autocast_dtype(precision, device)
        self.name = "base_only" if model.control is None else "ours"
        self.last_repaired = self.last_clamped = 0
        self.last_black = self.last_estimate_only = False
        self.last_seconds = 0.0

    def denoise(self, buffers: dict[str, np.ndarray], spp: int, skip: int | None = None, seed: int = 0,
                rotation: np.ndarray | None = None, variance: str | None = None, steps: int | None = None,
                start: str | None = None, samples: int = 1, with_std: bool = False, strength: float | None = None):
        """HDR (H, W, 3) float32; with ``with_std`` also the per-pixel standard deviation of the samples.
        ``strength`` (a model on OIDN's network only) must be unset or 1."""
        if strength is not None and float(strength) != 1.0:
            raise ConfigError(f"strength {strength}: only a model on OIDN's network (diffusion.base: oidn) scales "
                              "its Control Module's change; this one is on the stand-in base")
        t0 = time.perf_counter()
        buffers = {k: np.array(v, dtype=np.float32, copy=True) for k, v in buffers.items()}
        self.last_repaired = sum(repair_nonfinite(buffers).values())
        tonemap = self.meta.get("tonemap", "log")
        est, parts = self.estimator(buffers)
        noisy, aux = model_inputs(buffers, spp, rotation, tonemap, parts)
        self.last_black = not np.any(buffers["color"])
        self.last_estimate_only = est is not None and not has_renderer_buffers(buffers)
        if self.last_black:
            hdr, std = np.zeros_like(buffers["color"]), np.zeros_like(buffers["color"])
        elif self.last_estimate_only:   # not the buffers the network was trained on: the first estimate alone
            hdr, std = est, np.zeros_like(est)
        else:
            hdr, std = self._sample(noisy, aux, est, tonemap, skip, seed, variance, steps, start, samples)
            hdr, self.last_clamped = self._beyond_range(hdr, est if est is not None else buffers["color"])
        self.last_seconds = time.perf_counter() - t0
        return (hdr, std) if with_std else hdr

    def _sample(self, noisy, aux, est, tonemap, skip, seed, variance, steps, start, samples):
        t = lambda a: torch.from_numpy(a)[None].to(self.device)  # noqa: E731
        image = t(to_planar(est, tonemap)) if est is not None else None
        skip = int(self.meta.get("skip", 0) if skip is None else skip)
        # The requested sampling, checked like a config (a one-line ConfigError naming the key).
        f = dataclasses.replace(self.formulation, skip=skip, steps=self.formulation.steps if steps is None else steps,
                                start=start or self.formulation.start)
        mean, std = sample_tiled(self.model, t(noisy), t(aux), image=image, tile=self.tile, overlap=self.overlap,
                                 samples=samples, formulation=f, steps=steps, skip=skip, start=start, seed=seed,
                                 threshold_ratio=float(self.meta.get("threshold_ratio", 0.95)),
                                 autocast_dtype=self.autocast,
                                 variance=variance or self.meta.get("variance", "learned"))
        mean_m, std_m = mean[0].float().cpu().numpy(), std[0].float().cpu().numpy()
        hdr = from_model(torch.from_numpy(mean_m), tonemap).numpy()
        return np.moveaxis(hdr, 0, 2), np.moveaxis(hdr_std(mean_m, std_m, tonemap), 0, 2)

    def _beyond_range(self, hdr: np.ndarray, source: np.ndarray) -> tuple[np.ndarray, int]:
        """Pixels whose first estimate (or input) exceeds the model's range: the estimate's value where
        there is one, else the clamp at CLAMP; returns the image and how many pixels that touched."""
        over = (source > CLAMP).any(axis=2)
        if self.formulation.estimate != "none" and over.any():
            hdr = np.where(over[..., None], source, hdr)
        return np.ascontiguousarray(hdr, dtype=np.float32), int(over.sum())


def load_denoiser(folder: str | Path, device: str = "auto", base_only: bool = False, tile: int = 256,
                  overlap: int = 32, precision: str = "auto") -> Denoiser:
    """A trained run (``train.model.run_dir``); ``base_only`` drops the Control Module (the ablation). A run on
    OIDN's network (``diffusion.base: oidn``) is ``train.oidn_refine``'s denoiser, with the same interface."""
    from mcdenoise.pipeline import weights

    from . import oidn_refine
    if weights.kind(Path(folder)) == "oidn_control":
        return oidn_refine.load_refiner(folder, device, base_only)
    dev = pick_device(device)
    model, meta = load(folder, dev)
    if base_only:
        model.control = None
    return Denoiser(model, meta, dev, tile, overlap, precision, load_run_estimator(folder, meta, dev))
