"""Training of the diffusion denoiser (Control Module on a frozen base) and of the stand-in base.

    python -m pipeline train --model diffusion --spp 4         (make train SPP=4)
    torchrun --nproc_per_node 2 -m pipeline train --model diffusion --spp 4
    python -m pipeline pretrain                                (make pretrain)

Both run the loop every trainer shares (``pipeline.fit``: resume, best/last checkpoint, time
budget, summary); ``fit`` wraps a ``Job`` for it. What is diffusion-specific stands in separate
functions: ``make_optimizer``, ``optimisation_step`` (learning rate, loss, clipping, EMA),
``epoch_entry``, ``validation_score`` and the EMA helpers. Per step:

    x = GT_clean crop, x̃ = noisy crop (model space), F = condition, t ~ U{0..999}, ε ~ N(0, I)
    z_t = q_sample(x, t, ε);   loss = ‖ε − ε̂‖² + L_t(Σ_θ)      (train.diffusion.loss)

AdamW on the trainable parameters only, linear warm-up then cosine decay (a pure function of the
step, so nothing to restore), gradient clipping, bf16 autocast on CUDA. A NaN guard: a step
whose loss or gradient norm is not finite is skipped and counted (over the whole run);
``nan_limit`` in a row stop the run with an error. Every random draw comes from generators
seeded by (seed, epoch, step, rank) and the epoch's crops from ``default_rng([seed, epoch,
item])``: a resumed run continues exactly as the uninterrupted one. Checkpoints
(``last.safetensors``) hold the trainable weights, AdamW's moments and the torch RNG state, in
safetensors.

Under ``torchrun`` (DDP; gloo on CPU, NCCL on GPU) each rank takes every world-th item of the
epoch's permutation; rank 0 validates and writes; at the end the ranks compare a checksum of
their weights and fail loudly if they diverged.
"""
from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch.utils.data import DataLoader

from mcdenoise.pipeline.checkpoint import NanGuard, plot_curves
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.exr import atomic_write_json
from mcdenoise.pipeline.fit import Task, apply_update, fit as run_fit
from mcdenoise.pipeline.versions import machine

from . import diffusion


@dataclass
class Job:
    """What ``fit`` trains: a model, the module whose weights are saved, data and settings."""
    name: str
    folder: Path
    model: torch.nn.Module             # forward(z, noisy, aux, t) -> (B, 6, H, W)
    trainable: torch.nn.Module          # its state goes into last.safetensors
    params: list                        # what AdamW updates
    train_ds: object                    # items: noisy, aux (optional), target; set_epoch(epoch)
    validate: Callable | None           # (model) -> {"psnr": ..., ...} or None
    save_best: Callable                 # (record) -> None
    epochs: int
    batch_size: int
    lr: float
    weight_decay: float
    warmup_steps: int
    grad_clip: float
    nan_limit: int
    time_budget_s: float
    seed: int
    fingerprint: dict
    device: torch.device
    autocast: torch.dtype | None = None
    fmt: str = "mcdenoise-diffusion"
    title: str = ""
    objective: Callable | None = None   # (net, batch, gen, device, autocast) -> (loss, terms); None: IF's hybrid loss
    validate_initial: bool = False      # score the model before the first step (a candidate for "best")
    ema: float = 0.0                    # EMA decay of the trainable weights (validated and saved); 0: none
    epoch_steps: int = 0                # at most this many steps per epoch (a random subset); 0: all


def lr_factor(step: int, total: int, warmup: int) -> float:
    """Linear warm-up over ``warmup`` steps, then cosine decay to 0 at ``total``."""
    if warmup > 0 and step < warmup:
        return (step + 1) / warmup
    if total <= warmup:
        return 1.0
    p = min(1.0, (step - warmup) / max(1, total - warmup))
    return 0.5 * (1.0 + math.cos(math.pi * p))


def autocast_dtype(precision: str, device: torch.device) -> torch.dtype | None:
    if precision == "bf16" or (precision == "auto" and device.type == "cuda"):
        return torch.bfloat16
    return None


def dist_info() -> tuple[int, int]:
    """(rank, world size), initialising torch.distributed under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    import torch.distributed as dist
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if torch.cuda.is_available() else "gloo")
    return dist.get_rank(), world


def dist_shutdown() -> None:
    """Tear the process group down before the interpreter exits: gloo's threads otherwise abort the
    process at exit now and then ("terminate called without an active exception", exit -6)."""
    import torch.distributed as dist
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()   # no barrier: after an error on one rank it could hang


def checksum(module: torch.nn.Module) -> float:
    return float(sum(p.detach().double().sum() for p in module.parameters()))


def run_machine(device: torch.device, world: int = 1) -> dict:
    """What a run trained on, for its model card: the machine, torch, the device and the ranks."""
    return {**machine(), "torch": torch.__version__, "device": str(device), "ranks": world}


def fit(job: Job, quiet: bool = False) -> dict:
    """Train ``job`` to ``job.epochs`` (resuming from ``last.safetensors``; ``pipeline.fit``); return a summary."""
    return run_fit(_DiffusionTask(job), quiet=quiet)


# ---- what is diffusion-specific: optimizer, loss step, EMA, validation ----------------------------


def make_optimizer(job: Job) -> torch.optim.Optimizer:
    """AdamW on the trainable parameters (the learning rate is set per step: ``lr_factor``)."""
    return torch.optim.AdamW(job.params, lr=job.lr, weight_decay=job.weight_decay)


def optimisation_step(job: Job, net, objective: Callable, opt: torch.optim.Optimizer, ema, batch: dict,
                      gen: torch.Generator, step: int, total_steps: int) -> tuple[dict, bool]:
    """One step: the learning rate of ``step``, the objective's loss, clipped gradients, AdamW and
    the EMA; a non-finite loss or gradient norm changes nothing. ({"loss", "mse", "vb"}, finite)."""
    for g in opt.param_groups:
        g["lr"] = job.lr * lr_factor(step, total_steps, job.warmup_steps)
    loss, terms = objective(net, batch, gen, job.device, job.autocast)
    if not apply_update(loss, opt, job.params, job.grad_clip):
        return {}, False
    if ema is not None:
        ema.step(job.trainable.parameters())
    return {"loss": float(loss.detach()), "mse": float(terms["mse"]), "vb": float(terms["vb"])}, True


def epoch_entry(epoch: int, kept: list[dict], skipped: int, lr: float) -> dict:
    """Mean loss and its terms over the epoch's finite steps (nan / None without any)."""
    mean = {k: float(np.mean([t[k] for t in kept])) if kept else None for k in ("loss", "mse", "vb")}
    return {"epoch": epoch + 1, "train_loss": float("nan") if mean["loss"] is None else mean["loss"],
            "mse": mean["mse"], "vb": mean["vb"], "skipped_steps": skipped, "lr": lr}


def validation_score(entry: dict) -> float:
    """Higher is better: validation PSNR, else minus the training loss."""
    return entry["val"]["psnr"] if entry["val"] else -entry["train_loss"]


class _DiffusionTask(Task):
    """A ``Job`` as ``pipeline.fit`` trains it: rank ``r`` of ``world`` takes every world-th item of the
    epoch's permutation, at most ``epoch_steps`` batches of it; one NaN guard for the whole run."""

    minimize = False

    def __init__(self, job: Job):
        self.job = job
        self.rank, self.world = dist_info()
        self.name, self.folder, self.epochs, self.time_budget_s = job.name, job.folder, job.epochs, job.time_budget_s
        self.nan_limit, self.fingerprint, self.fmt, self.device = job.nan_limit, job.fingerprint, job.fmt, job.device
        self.state, self.validate_initial = job.trainable, job.validate_initial
        self.optimizers = self.opt = make_optimizer(job)
        self.ema = make_ema(job.trainable, job.ema)
        self._guard = None

    def resume(self, record: dict, extra: dict) -> None:
        if self.ema is not None:
            self.ema.shadow_params = [extra[f"ema.{i}"].to(self.device) for i in range(len(self.ema.shadow_params))]
            self.ema.optimization_step = int(record["ema_step"])

    def prepare(self) -> None:
        job = self.job
        self.net = job.model
        if self.world > 1:
            from torch.nn.parallel import DistributedDataParallel as DDP
            self.net = DDP(job.model, device_ids=[job.device.index] if job.device.type == "cuda" else None)
        self.objective = job.objective or diffusion.objective(job.device)
        self.per_rank = len(job.train_ds) // self.world
        self.steps_per_epoch = max(1, self.per_rank // job.batch_size)
        if job.epoch_steps > 0:   # a subset per epoch: validation, checkpoint and budget come more often
            self.steps_per_epoch = min(self.steps_per_epoch, job.epoch_steps)
            self.per_rank = min(self.per_rank, self.steps_per_epoch * job.batch_size)
        self.total_steps = job.epochs * self.steps_per_epoch
        self._guard = NanGuard(job.name, job.nan_limit, TrainError)

    def guard(self) -> NanGuard:
        return self._guard

    def batches(self, epoch: int):
        job = self.job
        job.train_ds.set_epoch(epoch)
        order = np.random.default_rng([job.seed, epoch]).permutation(len(job.train_ds))
        mine = order[self.rank::self.world][:self.per_rank].tolist()
        job.model.train()
        return DataLoader(job.train_ds, batch_size=job.batch_size, sampler=mine, drop_last=True, num_workers=0)

    def step(self, batch: dict, epoch: int, index: int) -> tuple[dict, bool]:
        gen = torch.Generator().manual_seed(
            int(np.random.default_rng([self.job.seed, epoch, index, self.rank]).integers(2**62)))
        return optimisation_step(self.job, self.net, self.objective, self.opt, self.ema, batch, gen,
                                 epoch * self.steps_per_epoch + index, self.total_steps)

    def entry(self, epoch: int, kept: list[dict], skipped: int) -> dict:
        return epoch_entry(epoch, kept, skipped, self.opt.param_groups[0]["lr"])

    def initial_entry(self) -> dict:
        # With a zero-initialised residual the untrained model is the first estimate itself, so
        # training can only be kept where validation improves it.
        return {"epoch": 0, "train_loss": None, "mse": None, "vb": None, "skipped_steps": 0, "lr": 0.0}

    def validate(self) -> dict | None:
        return self.job.validate(self.job.model) if self.job.validate is not None else None

    def evaluation(self):
        return ema_weights(self.ema, self.job.trainable)   # validated and saved: the EMA of the weights, if any

    def score(self, entry: dict) -> float:
        return validation_score(entry)

    def save_best(self, entry: dict) -> None:
        self.job.save_best({"epoch": entry["epoch"], "metrics": entry["val"], "train_loss": entry["train_loss"]})

    def write_history(self, history: list, best: dict | None) -> None:
        _plot(self.job, history)
        atomic_write_json(self.folder / "train.json", {"name": self.name, "history": history, "best": best,
                                                       "machine": run_machine(self.device, self.world)})

    def checkpoint(self) -> tuple[dict, dict | None]:
        if self.ema is None:
            return {}, None
        return ({"ema_step": self.ema.optimization_step},
                {f"ema.{i}": p for i, p in enumerate(self.ema.shadow_params)})

    def finish(self) -> None:
        if self.world > 1:
            _check_in_sync(self.job.trainable, self.world)

    def epoch_line(self, entry: dict) -> str:
        v = entry["val"]
        return (f"{self.name} epoch {entry['epoch']}: loss {entry['train_loss']:.4f} (mse {entry['mse']:.4f}, "
                f"vb {entry['vb']:.4f})" + (f", val PSNR {v['psnr']:.2f} dB (noisy {v['noisy_psnr']:.2f})" if v else ""))

    def best_text(self, best: dict) -> str:
        if best.get("val"):
            v = best["val"]
            return f"best epoch {best['epoch']}: val PSNR {v['psnr']:.2f} dB vs noisy {v['noisy_psnr']:.2f} dB"
        return super().best_text(best)

    def summary_fields(self) -> dict:
        return {"name": self.name, **({"skipped_steps": self._guard.skipped} if self._guard else {})}


def make_ema(module: torch.nn.Module, decay: float):
    """``diffusers``' EMAModel over ``module``'s weights (with its warm-up: early on the average follows
    the weights closely), or None for ``decay`` 0."""
    if decay <= 0:
        return None
    from diffusers.training_utils import EMAModel
    return EMAModel(module.parameters(), decay=decay, use_ema_warmup=True, power=0.75)


@contextlib.contextmanager
def ema_weights(ema, module: torch.nn.Module):
    """Inside: ``module`` holds the EMA weights; after: its own again."""
    if ema is None:
        yield
        return
    ema.store(module.parameters())
    ema.copy_to(module.parameters())
    try:
        yield
    finally:
        ema.restore(module.parameters())


def _check_in_sync(module: torch.nn.Module, world: int) -> None:
    import torch.distributed as dist
    mine = torch.tensor([checksum(module)], dtype=torch.float64)
    every = [torch.zeros_like(mine) for _ in range(world)]
    dist.all_gather(every, mine)
    values = [float(v) for v in every]
    if max(values) - min(values) > 1e-9 * max(1.0, abs(values[0])):
        raise TrainError(f"DDP ranks diverged: weight checksums {values}")
    if dist.get_rank() == 0:
        print(f"DDP: {world} ranks in sync (weight checksum {values[0]:.6f})", flush=True)


def _plot(job: Job, history: list[dict]) -> None:
    curves = {"train loss": [(h["epoch"], h["train_loss"]) for h in history
                             if h["train_loss"] is not None and np.isfinite(h["train_loss"])]}
    right = {}
    if any(h.get("val") for h in history):
        right = {"val PSNR (dB)": [(h["epoch"], h["val"]["psnr"]) for h in history if h.get("val")],
                 "noisy input PSNR": [(h["epoch"], h["val"]["noisy_psnr"]) for h in history if h.get("val")]}
    plot_curves(job.folder / "loss.png", curves, job.title or job.name, right=right, right_label="PSNR (dB)")
