"""Denoise a frame with a trained run: the evaluator's and ``python -m pipeline denoise``'s entry point.

    den = load_denoiser(run_dir(cfg, 4))                 # or base_only=True: the ablation row
    hdr = den.denoise(store.read(scene, frame, 4), spp=4, skip=0, seed=0)   # (H, W, 3) float32

``buffers`` are what ``Store.read`` returns (HxWxC arrays by buffer name, variances included);
missing feature buffers count as their background value. Non-finite input values are replaced
by 0 and counted in ``den.last_repaired`` (never passed to the network). Frames larger than
``diffusion.tile`` are denoised in overlapping tiles, so memory is bounded at any size.
The output is HDR radiance in [0, 6] (the model's range, as in the paper).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from pipeline.numerics import repair_nonfinite

from .data import from_model, model_inputs
from .model import load, run_dir
from .sampler import sample_tiled
from .train import autocast_dtype, pick_device


__all__ = ["Denoiser", "load_denoiser", "run_dir"]


class Denoiser:
    def __init__(self, model, meta: dict, device: torch.device, tile: int = 256, overlap: int = 32,
                 precision: str = "auto"):
        self.model, self.meta, self.device = model, meta, device
        self.tile, self.overlap = int(tile), int(overlap)
        self.autocast = autocast_dtype(precision, device)
        self.name = "base_only" if model.control is None else "ours"
        self.last_repaired = 0
        self.last_seconds = 0.0

    def denoise(self, buffers: dict[str, np.ndarray], spp: int, skip: int | None = None, seed: int = 0,
                rotation: np.ndarray | None = None, variance: str | None = None) -> np.ndarray:
        t0 = time.perf_counter()
        buffers = {k: np.array(v, dtype=np.float32, copy=True) for k, v in buffers.items()}
        self.last_repaired = sum(repair_nonfinite(buffers).values())
        tonemap = self.meta.get("tonemap", "log")
        noisy, aux = model_inputs(buffers, spp, rotation, tonemap)
        noisy_t = torch.from_numpy(noisy)[None].to(self.device)
        aux_t = torch.from_numpy(aux)[None].to(self.device)
        skip = int(self.meta.get("skip", 0) if skip is None else skip)
        out = sample_tiled(self.model, noisy_t, aux_t, tile=self.tile, overlap=self.overlap, skip=skip, seed=seed,
                           threshold_ratio=float(self.meta.get("threshold_ratio", 0.95)),
                           autocast_dtype=self.autocast,
                           variance=variance or self.meta.get("variance", "learned"))
        hdr = from_model(out[0].float().cpu(), tonemap).numpy()
        self.last_seconds = time.perf_counter() - t0
        return np.ascontiguousarray(np.moveaxis(hdr, 0, 2), dtype=np.float32)


def load_denoiser(folder: str | Path, device: str = "auto", base_only: bool = False, tile: int = 256,
                  overlap: int = 32, precision: str = "auto") -> Denoiser:
    """A trained run (``train.model.run_dir``); ``base_only`` drops the Control Module (the ablation)."""
    dev = pick_device(device)
    model, meta = load(folder, dev)
    if base_only:
        model.control = None
    return Denoiser(model, meta, dev, tile, overlap, precision)
