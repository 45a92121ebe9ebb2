"""Training of the diffusion denoiser (Control Module on a frozen base) and of the stand-in base.

    python -m pipeline train --model diffusion --spp 4         (make train SPP=4)
    torchrun --nproc_per_node 2 -m pipeline train --model diffusion --spp 4
    python -m pipeline pretrain                                (make pretrain)

One loop (``fit``) for both; per step:

    x = GT_clean crop, x̃ = noisy crop (model space), F = condition, t ~ U{0..999}, ε ~ N(0, I)
    z_t = q_sample(x, t, ε);   loss = ‖ε − ε̂‖² + L_t(Σ_θ)      (train.diffusion.loss)

AdamW on the trainable parameters only, linear warm-up then cosine decay (a pure function of the
step, so nothing to restore), gradient clipping, bf16 autocast on CUDA. A NaN guard: a step
whose loss or gradient norm is not finite is skipped and counted; ``nan_limit`` in a row stop the
run with an error. Every random draw comes from generators seeded by (seed, epoch, step, rank)
and the epoch's crops from ``default_rng([seed, epoch, item])``: a resumed run continues exactly
as the uninterrupted one. Checkpoints (``last.safetensors``) hold the trainable weights, AdamW's
moments and the torch RNG state, in safetensors.

Under ``torchrun`` (DDP; gloo on CPU, NCCL on GPU) each rank takes every world-th item of the
epoch's permutation; rank 0 validates and writes; at the end the ranks compare a checksum of
their weights and fail loudly if they diverged.
"""
from __future__ import annotations

import contextlib
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch.utils.data import DataLoader

from pipeline.checkpoint import NanGuard, load_last, plot_curves, save_last
from pipeline.errors import TrainError
from pipeline.exr import atomic_write_json
from pipeline.progress import progress
from pipeline.versions import machine

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
    """Train ``job`` to ``job.epochs`` (resuming from ``last.safetensors``); return a summary."""
    t_start = time.perf_counter()
    rank, world = dist_info()
    quiet = quiet or rank != 0
    model, folder, device = job.model, job.folder, job.device
    opt = torch.optim.AdamW(job.params, lr=job.lr, weight_decay=job.weight_decay)
    last = folder / "last.safetensors"
    history: list[dict] = []
    best: dict | None = None
    start = 0
    ema = _make_ema(job)
    if last.exists():
        extra: dict = {}
        record = load_last(last, job.trainable, opt, device, extra=extra, fingerprint=job.fingerprint)
        start, history, best = int(record["epoch"]), record["history"], record["best"]
        if ema is not None:
            ema.shadow_params = [extra[f"ema.{i}"].to(device) for i in range(len(ema.shadow_params))]
            ema.optimization_step = int(record["ema_step"])
    if start >= job.epochs:
        summary = _summary(job, history, best, 0, time.perf_counter() - t_start)
        if not quiet:
            print(f"{job.name}: already trained ({start} epochs); {summary['line']}")
        return summary

    net = model
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel as DDP
        net = DDP(model, device_ids=[device.index] if device.type == "cuda" else None)
    objective = job.objective or diffusion.objective(device)
    if start == 0 and job.validate_initial and job.validate is not None and rank == 0:
        best = _initial(job, history)   # the EMA equals the weights here
    per_rank = len(job.train_ds) // world
    steps_per_epoch = max(1, per_rank // job.batch_size)
    if job.epoch_steps > 0:   # a subset per epoch: validation, checkpoint and budget come more often
        steps_per_epoch = min(steps_per_epoch, job.epoch_steps)
        per_rank = min(per_rank, steps_per_epoch * job.batch_size)
    total_steps = job.epochs * steps_per_epoch
    guard, trained = NanGuard(job.name, job.nan_limit, TrainError), 0
    for epoch in range(start, job.epochs):
        job.train_ds.set_epoch(epoch)
        order = np.random.default_rng([job.seed, epoch]).permutation(len(job.train_ds))
        mine = order[rank::world][:per_rank].tolist()
        loader = DataLoader(job.train_ds, batch_size=job.batch_size, sampler=mine, drop_last=True, num_workers=0)
        model.train()
        losses, parts = [], {"mse": [], "vb": []}
        bar = progress(loader, desc=f"{job.name} epoch {epoch + 1}/{job.epochs}", unit="step", disable=quiet,
                       leave=False)
        for i, batch in enumerate(bar):
            step = epoch * steps_per_epoch + i
            for g in opt.param_groups:
                g["lr"] = job.lr * lr_factor(step, total_steps, job.warmup_steps)
            gen = torch.Generator().manual_seed(int(np.random.default_rng([job.seed, epoch, i, rank]).integers(2**62)))
            batch = {k: v.to(device) for k, v in batch.items()}
            loss, terms = objective(net, batch, gen, device, job.autocast)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            norm = torch.nn.utils.clip_grad_norm_(job.params, job.grad_clip if job.grad_clip > 0 else float("inf"))
            if not guard.ok(bool(torch.isfinite(loss) and torch.isfinite(norm)), epoch, i):
                continue
            opt.step()
            if ema is not None:
                ema.step(job.trainable.parameters())
            losses.append(float(loss.detach()))
            for k in parts:
                parts[k].append(float(terms[k]))
            bar.set_postfix(loss=f"{np.mean(losses):.4f}")
        entry = {"epoch": epoch + 1, "train_loss": float(np.mean(losses)) if losses else float("nan"),
                 "mse": float(np.mean(parts["mse"])) if losses else None,
                 "vb": float(np.mean(parts["vb"])) if losses else None,
                 "skipped_steps": guard.skipped, "lr": opt.param_groups[0]["lr"]}
        if rank == 0:
            with _ema_weights(ema, job.trainable):   # validated and saved: the EMA of the weights, if any
                entry["val"] = job.validate(model) if job.validate is not None else None
                entry["seconds"] = round(time.perf_counter() - t_start, 2)
                history.append(entry)
                score = entry["val"]["psnr"] if entry["val"] else -entry["train_loss"]
                if best is None or score > best["score"]:
                    best = {"epoch": epoch + 1, "score": score, "val": entry["val"], "train_loss": entry["train_loss"]}
                    job.save_best({"epoch": epoch + 1, "metrics": entry["val"], "train_loss": entry["train_loss"]})
            # last.safetensors is the commit point of an epoch, so it is written last: a kill before it
            # reruns the epoch (same result) and rewrites the files above.
            _plot(job, history)
            atomic_write_json(folder / "train.json", {"name": job.name, "history": history, "best": best,
                                                      "machine": run_machine(device, world)})
            state = {"epoch": epoch + 1, "history": history, "best": best, "fingerprint": job.fingerprint}
            extras = None
            if ema is not None:
                state["ema_step"] = ema.optimization_step
                extras = {f"ema.{i}": p for i, p in enumerate(ema.shadow_params)}
            save_last(last, job.trainable, opt, state, job.fmt, extra=extras)
            if not quiet:
                v = entry["val"]
                print(f"{job.name} epoch {epoch + 1}: loss {entry['train_loss']:.4f} (mse {entry['mse']:.4f}, "
                      f"vb {entry['vb']:.4f})" + (f", val PSNR {v['psnr']:.2f} dB (noisy {v['noisy_psnr']:.2f})"
                                                  if v else ""), flush=True)
        trained += 1
        if world > 1:
            torch.distributed.barrier()
        if job.time_budget_s > 0 and time.perf_counter() - t_start >= job.time_budget_s and epoch + 1 < job.epochs:
            if not quiet:
                print(f"{job.name}: time budget of {job.time_budget_s:g} s reached after epoch {epoch + 1}; "
                      "rerun to resume")
            break
    if world > 1:
        _check_in_sync(job.trainable, world)
    summary = _summary(job, history, best, trained, time.perf_counter() - t_start)
    summary["skipped_steps"] = guard.skipped
    if not quiet:
        print(summary["line"], flush=True)
    return summary


def _make_ema(job: Job):
    """``diffusers``' EMAModel over the trainable weights (with its warm-up: early on the average follows
    the weights closely), or None."""
    if job.ema <= 0:
        return None
    from diffusers.training_utils import EMAModel
    return EMAModel(job.trainable.parameters(), decay=job.ema, use_ema_warmup=True, power=0.75)


@contextlib.contextmanager
def _ema_weights(ema, module: torch.nn.Module):
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


def _initial(job: Job, history: list[dict]) -> dict:
    """Epoch 0: the untrained model's validation score, saved as the best so far. With a zero-initialised
    residual this is the first estimate itself, so training can only be kept where validation improves it."""
    val = job.validate(job.model)
    history.append({"epoch": 0, "train_loss": None, "mse": None, "vb": None, "skipped_steps": 0,
                    "lr": 0.0, "val": val, "seconds": 0.0})
    job.save_best({"epoch": 0, "metrics": val, "train_loss": None})
    return {"epoch": 0, "score": val["psnr"], "val": val, "train_loss": None}


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


def _summary(job: Job, history: list, best: dict | None, trained: int, seconds: float) -> dict:
    epochs = history[-1]["epoch"] if history else 0
    line = f"{job.name}: {epochs} epochs ({trained} this run, {seconds:.1f} s)"
    if best and best.get("val"):
        v = best["val"]
        line += f"; best epoch {best['epoch']}: val PSNR {v['psnr']:.2f} dB vs noisy {v['noisy_psnr']:.2f} dB"
    elif best:
        line += f"; best epoch {best['epoch']}: train loss {best['train_loss']:.4f}"
    line += f" -> {job.folder}"
    return {"name": job.name, "folder": str(job.folder), "epochs": epochs, "trained_epochs": trained,
            "best": best, "seconds": seconds, "line": line}
