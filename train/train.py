"""Training: the Control Module on OIDN's frozen network, trained on a config's store.

    make train SPP=any      → python -m pipeline train --model diffusion --spp any → train(cfg, "any")
                            → runs/<config>/diffusion_sppany[_<name>]/

``train`` is the run written out in order. The model (``train.model``): OIDN frozen and a new Control
Module, or both from a trained model folder (``diffusion.init``, a warm start). The data (``train.data``):
the store's pack, crops with OIDN's augmentation and buffer-group dropout, the val frames. AdamW on the
Control Module only (warm-up, cosine decay) and an EMA of its weights; ``last.safetensors`` resumes them.
Epoch 0 validates OIDN itself. Each step noises the residual around the base's output at a t drawn with
``t_focus`` on the sampler's steps (``train.sampler``), the network predicts x̂₀, the loss is each crop's
error relative to OIDN's (``train.loss``) weighted by min-SNR, and the optimiser steps (a non-finite step
is skipped; ``nan_limit`` in a row stop the run). Each epoch ends with validation on the EMA weights (the
sampler, PSNR against the base's), the best checkpoint and ``keep_epochs``, the history and
``last.safetensors``, its commit point; ``time_budget_s`` stops after an epoch (a rerun resumes). σ is
fitted at the end (``train.infer.calibrate``). DDP under torchrun: every rank steps, rank 0 validates and
writes. The run folder: ``control.safetensors`` (the Control Module, EMA), ``base.tza`` (the frozen base's
float16 weights, so the run is self-contained), ``model.json``, ``last.safetensors``, ``train.json``,
``loss.png``, and ``epoch<N>/`` for each of ``diffusion.keep_epochs`` (model folders of those epochs).
"""
from __future__ import annotations

import contextlib
import hashlib
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from mcdenoise.pipeline import config as config_mod, weights
from mcdenoise.pipeline.checkpoint import load_last, save_last
from mcdenoise.pipeline.config import Config, pick_device
from mcdenoise.pipeline.errors import ConfigError, TrainError
from mcdenoise.pipeline.exr import atomic_write_json, read_json
from mcdenoise.pipeline.metrics import PSNR_CEILING, psnr
from mcdenoise.pipeline.progress import progress
from mcdenoise.pipeline.store import sha256
from mcdenoise.pipeline.weights import read_tza

from . import oidn
from .data import Crops, StoreSource, input_record, pack_keys
from .loss import relative_loss
from .model import (
    FORMAT,
    NETWORK,
    ControlledOIDN,
    UNet,
    cond_names,
    load,
    network_output,
    reads_history,
    run_dir,
    save,
    widen_control,
)
from .sampler import Formulation, sample, snr_weight

# The σ scales a fit may find: the samples' spread within a factor 100 of the error either way (the shipped
# model's is 2.82); outside it the spread does not track the error on these frames.
SIGMA_PLAUSIBLE = (0.01, 100.0)

# What a warm-started run copies from its start's model.json besides the weights: how the model is used
KEPT = ("control_without_groups",)
# The settings of the config a resume must share besides the seed, the base, the start and the formulation
FINGERPRINT_KEYS = ("crop", "batch_size", "crops_per_frame", "epoch_steps", "lr", "weight_decay", "warmup_steps",
                    "grad_clip", "ema", "epochs", "hdr_weight", "dropout")


@dataclass
class Run:
    """A run's model and optimiser, and where it writes (``setup``)."""
    cfg: Config
    name: str
    folder: Path
    source: StoreSource
    spps: list[int]
    device: torch.device
    rank: int
    world: int
    says: bool                      # prints its lines: not --quiet, and rank 0
    autocast: torch.dtype | None
    model: ControlledOIDN
    blob: bytes                     # the frozen base's float16 weights (base.tza)
    base_what: str
    network: str
    base_blend: float | None
    form: Formulation
    train_steps: list[int]
    kept: dict                      # a warm start's KEPT fields
    params: list
    opt: torch.optim.Optimizer
    ema: object                     # diffusers' EMAModel, or None
    fingerprint: dict


@dataclass
class Data:
    """The training crops and the val frames (``load_data``), and what the steps draw from."""
    crops: Crops
    val: list[dict]                 # rank 0 only
    per_rank: int
    steps_per_epoch: int
    total_steps: int
    focus: torch.Tensor             # the timesteps t is drawn from
    noise: object                   # the DDPM scheduler that noises
    net: torch.nn.Module            # the model, DDP-wrapped under torchrun


def train(cfg: Config, spp="any", quiet: bool = False) -> dict:
    """Train (or resume) the Control Module on OIDN; the summary (folder, epochs, best, seconds, line)."""
    try:
        run = setup(cfg, spp, quiet)
        start, history, best = resume(run)
        if start >= cfg.diffusion.epochs:
            # Already trained: only the report, and the history files again.
            if history:
                write_history(run, history, best)
            summary = summarize(run, history, best, 0, 0.0)
            if run.says:
                print(f"{run.name}: already trained ({start} epochs); {summary['line']}")
            return summary
        data = load_data(run)
        # The run's clock (time budget, ``seconds``) starts with the data loaded: a pack built first, once for every
        # run on the store (most of an hour for a large one), would leave a budgeted run fewer epochs the first time.
        t_start = time.perf_counter()
        if start == 0 and run.rank == 0:
            # Epoch 0, the model before any step (OIDN exactly for a new, zero-initialised Control Module; the start's
            # model for a warm start): the run must beat it to keep anything.
            best = validate_start(run, data.val, history)
        best, trained = run_epochs(run, data, history, best, start, t_start)
        calibrate_sigma(run, data.val)
        if run.world > 1:
            # Leave together: a rank that tears gloo down while its peer still writes files can abort the peer
            # at exit ("terminate called without an active exception"). Only on success: after an error a
            # barrier could wait for a rank that is gone.
            torch.distributed.barrier()
        summary = summarize(run, history, best, trained, time.perf_counter() - t_start)
        if run.says:
            print(summary["line"], flush=True)
        return summary
    finally:
        dist_shutdown()


def run_epochs(run: Run, data: Data, history: list, best: dict | None, start: int,
               t_start: float) -> tuple[dict | None, int]:
    """Epochs ``start``…``diffusion.epochs``, or until the time budget; (the best, the epochs trained)."""
    d, seed = run.cfg.diffusion, run.cfg.seed
    skipped = in_row = trained = 0      # non-finite steps: in this invocation, in a row (across epochs too)
    for epoch in range(start, d.epochs):
        kept = []
        bar = progress(epoch_batches(run, data, epoch), desc=f"{run.name} epoch {epoch + 1}/{d.epochs}", unit="step",
                       disable=not run.says, leave=False)
        for i, batch in enumerate(bar):
            batch = {k: v.to(run.device) for k, v in batch.items()}
            x, cond, target, scale = batch["x"], batch["cond"], batch["target"], batch["scale"]
            # t and the noise from (seed, epoch, step, rank): a resumed run draws what the uninterrupted one drew.
            gen = torch.Generator().manual_seed(int(np.random.default_rng([seed, epoch, i, run.rank]).integers(2 ** 62)))
            for g in run.opt.param_groups:
                g["lr"] = d.lr * lr_factor(epoch * data.steps_per_epoch + i, data.total_steps, d.warmup_steps)
            # The diffused variable: the residual around the base's output, in units of the residual scale.
            feats, est = run.model.estimate(x)
            y = (target - est) / run.form.residual_scale
            t = run.form.draw_t(x.shape[0], data.focus, gen).to(run.device)
            z = data.noise.add_noise(y, torch.randn(y.shape, generator=gen).to(run.device), t)
            with torch.autocast(run.device.type, dtype=run.autocast, enabled=run.autocast is not None):
                out, _ = data.net(x, cond, z, t, base=(feats, est))
            per_crop, terms = relative_loss(out.float(), est, target, scale, d.hdr_weight)
            # min-SNR-γ: x̂₀'s error weighted by the SNR capped at γ (the nearly clean t must not dominate), floored.
            w = snr_weight(data.noise, t, run.form.snr_gamma, run.form.snr_floor).to(run.device)
            loss = (w * per_crop).mean()
            run.opt.zero_grad(set_to_none=True)
            loss.backward()
            # max_norm inf measures without clipping (the gradients are multiplied by exactly 1).
            norm = torch.nn.utils.clip_grad_norm_(run.params, d.grad_clip if d.grad_clip > 0 else float("inf"))
            if not (torch.isfinite(loss) and torch.isfinite(norm)):
                # Skipped: one bad batch must not poison the weights; many in a row mean bad data or a bad lr.
                run.opt.zero_grad(set_to_none=True)
                skipped, in_row = skipped + 1, in_row + 1
                if in_row >= int(d.nan_limit):
                    raise TrainError(nan_message(run.name, in_row, epoch, i))
                continue
            run.opt.step()
            if run.ema is not None:
                run.ema.step(run.model.control.parameters())
            in_row = 0
            kept.append({"loss": float(loss.detach()), **{k: float(v) for k, v in terms.items()}})
            bar.set_postfix(loss=f"{np.mean([s['loss'] for s in kept]):.4f}")
        entry = epoch_entry(epoch, kept, skipped, run.opt.param_groups[0]["lr"])
        if run.rank == 0:
            best = end_epoch(run, data.val, entry, history, best, t_start)
            if run.says:
                print(epoch_line(run.name, entry), flush=True)
        trained += 1
        if run.world > 1:
            torch.distributed.barrier()
        if d.time_budget_s > 0 and time.perf_counter() - t_start >= d.time_budget_s and epoch + 1 < d.epochs:
            if run.says:
                print(f"{run.name}: time budget of {d.time_budget_s:g} s reached after epoch {epoch + 1}; "
                      "rerun to resume")
            break
    return best, trained


# ---- the stages of a run --------------------------------------------------------------------------


def setup(cfg: Config, spp, quiet: bool) -> Run:
    """The config's run: OIDN frozen (its float16 blob kept with the run) and a new Control Module, or both from
    a trained model folder (``diffusion.init``: a warm start); AdamW on the Control Module, its EMA."""
    d = cfg.diffusion
    init = Path(d.init) if d.init else None
    # the base's network: a warm start keeps its model's
    init_meta = weights.read_record(init, "oidn_control", "") if init is not None else {}
    network = init_meta.get("base_network", NETWORK) if init is not None else d.base_network
    # a model that reads the past keeps reading it: a warm start from one needs no diffusion.history
    history = d.history or reads_history(init_meta.get("cond_channels", []))
    source = StoreSource(cfg, network, history)
    spps = source.spps(spp)
    rank, world = dist_info()
    folder = run_dir(cfg, spp)
    device = pick_device(d.device)
    says = not quiet and rank == 0
    start, blob, base_what, base_blend, form, train_steps, kept = base_and_start(cfg, init, device, says)
    torch.manual_seed(cfg.seed)         # the Control Module's initial weights
    model = ControlledOIDN(UNet.from_tza(read_tza(blob, base_what)), len(cond_names(history)),
                           history=history).to(device)
    if start is not None:
        state = start.control.state_dict()
        if history and not start.history:   # the history's columns start at zero: epoch 0 is the start's model
            state = widen_control(state, model.control.layout, model.base.in_channels, cond_names(), cond_names(True))
        model.control.load_state_dict(state)
    params = model.trainable_parameters()
    opt = torch.optim.AdamW(params, lr=d.lr, weight_decay=d.weight_decay)
    fingerprint = {"spp": str(spp), "seed": cfg.seed, "base_sha256": hashlib.sha256(blob).hexdigest(),
                   # the start by content, not only by path: a replaced folder must not resume this run
                   **({"init": str(init), "init_sha256": sha256(init / "control.safetensors")} if init is not None
                      else {}),
                   "formulation": form.record(), "train_steps": train_steps,
                   **{k: getattr(d, k) for k in FINGERPRINT_KEYS},
                   # only with history: the fingerprint of a run without it stays what it was (it still resumes)
                   **({"history": True, "history_dropout": d.history_dropout} if history else {}),
                   # the input a model that reads the past trains on, where it is averaged (train.history)
                   **({"input": input_record(source.window)} if history and input_record(source.window) else {})}
    return Run(cfg, folder.name, folder, source, spps, device, rank, world, says, autocast_dtype(d.precision, device),
               model, blob, base_what, network, base_blend, form, train_steps, kept, params, opt,
               make_ema(model.control, d.ema), fingerprint)


def base_and_start(cfg: Config, init: Path | None, device: torch.device, says: bool) -> tuple:
    """(the start's model or None, the base's blob, what it is, its blend, the formulation, train_steps, KEPT
    fields): a warm start's (``warm_start_recipe``), else OIDN's weights of the config and its formulation."""
    d = cfg.diffusion
    form = Formulation.from_config(d)
    if init is None:
        blob, base_what = base_blob(cfg)
        return None, blob, base_what, {"oidn": 0.0, "oidn_ft": cfg.oidn_ft.blend}.get(d.base), form, list(d.train_steps), {}
    start, meta = load(init, device)
    blob, base_what = (init / meta["base"]).read_bytes(), f"{init}/{meta['base']}"
    form, train_steps, differ = warm_start_recipe(d, meta)
    if differ and says:
        print(f"diffusion.init={init}: the run keeps that model's formulation; not used: {'; '.join(differ)}",
              flush=True)
    return start, blob, base_what, meta.get("base_blend"), form, train_steps, {k: meta[k] for k in KEPT if k in meta}


def base_blob(cfg: Config) -> tuple[bytes, str]:
    """(the base's float16 TZA blob, what it is) of a new run: ``diffusion.base`` 'oidn' (OIDN's
    ``diffusion.base_network``, from ``oidn.weights`` or pyoidn), 'oidn_ft' (this config's oidn_ft run of that
    network, as exported) or a .tza file of it."""
    base, network = cfg.diffusion.base, cfg.diffusion.base_network
    if base == "oidn":
        return oidn.weights_blob(network, oidn.weights_source(network, cfg.oidn.weights)), f"OIDN {network}"
    if base == "oidn_ft":
        from .baselines.oidn_ft import export_blob, load_run
        folder = config_mod.run_dir(cfg, "oidn_ft", variant=network)
        return export_blob(load_run(folder, cfg)[0]), f"oidn_ft run {folder} (blend {cfg.oidn_ft.blend:g})"
    return oidn.weights_blob(network, base), str(base)


def warm_start_recipe(d, meta: dict) -> tuple[Formulation, list[int], list[str]]:
    """What a warm start (``diffusion.init``) keeps of the model it starts from: its formulation (the residual
    scale its Control Module's output is read at, the schedule, the sampler, t_focus, the loss's normalisation)
    and the sampler step counts it trained for, so that epoch 0 is that model and training goes on with its
    recipe; the config's keys set the optimiser and the data. Returns (formulation, train_steps, the config's
    keys that differ from the model's, as notes)."""
    form = Formulation.from_record(meta["formulation"])
    steps = list(meta.get("settings", {}).get("train_steps", d.train_steps))
    mine = Formulation.from_config(d)
    differ = [f"diffusion.{k}={getattr(mine, k)} (the model's: {getattr(form, k)})" for k in form.record()
              if k not in ("estimate", "residual") and getattr(mine, k) != getattr(form, k)]
    if list(d.train_steps) != steps:
        differ.append(f"diffusion.train_steps={list(d.train_steps)} (the model's: {steps})")
    return form, steps, differ


def resume(run: Run) -> tuple[int, list, dict | None]:
    """(the epochs done, the history, the best) from ``last.safetensors``, whose weights, optimiser moments, torch
    RNG and EMA are restored in place (refused when the fingerprint changed); (0, [], None) for a new run."""
    if run.rank == 0 and run.folder.is_dir():
        # Temporary files of a write a kill interrupted (one trainer per run folder: all stale).
        for tmp in run.folder.glob(".*.tmp"):
            tmp.unlink(missing_ok=True)
    last = run.folder / "last.safetensors"
    if not last.exists():
        return 0, [], None
    extra: dict = {}
    record = load_last(last, run.model.control, run.opt, run.device, extra=extra, fingerprint=run.fingerprint)
    if run.ema is not None:
        run.ema.shadow_params = [extra[f"ema.{i}"].to(run.device) for i in range(len(run.ema.shadow_params))]
        run.ema.optimization_step = int(record["ema_step"])
    return int(record["epoch"]), record["history"], record["best"]


def check_steps(crops: int, batch_size: int, frames: int, per_frame: int) -> None:
    """An epoch of ``crops`` crops per rank takes at least one optimiser step (full batches only), else a
    ConfigError naming the keys to change: a run that would step zero times must not look trained."""
    if crops < batch_size:
        raise ConfigError(f"diffusion.batch_size {batch_size}: more than the {crops} training crops an epoch has "
                          f"({frames} train frames x diffusion.crops_per_frame {per_frame}), so no optimiser step "
                          f"would run; set diffusion.batch_size={max(1, crops)} or raise diffusion.crops_per_frame")


def load_data(run: Run) -> Data:
    """The store's training pack as crops, this rank's share of them per epoch, the val frames (rank 0), and the
    model wrapped in DDP under torchrun."""
    t = time.perf_counter()
    d = run.cfg.diffusion
    frames = (len(pack_keys(run.source.train_keys, run.source.history))
              + sum(len(pack_keys(keys, run.source.history)) for _, keys in run.source.extra))
    check_steps(frames * d.crops_per_frame // run.world, d.batch_size, frames, d.crops_per_frame)
    pack = run.source.train_pack(not run.says, build=run.rank == 0)
    crops = Crops(pack, d.crop, d.crops_per_frame, run.cfg.seed, run.spps, dropout=d.dropout,
                  history_dropout=d.history_dropout)
    per_rank = len(crops) // run.world
    check_steps(per_rank, d.batch_size, len(crops.frames), d.crops_per_frame)
    steps_per_epoch = per_rank // d.batch_size
    if d.epoch_steps:
        steps_per_epoch = min(steps_per_epoch, d.epoch_steps)
        per_rank = min(per_rank, steps_per_epoch * d.batch_size)
    focus, noise = run.form.train_timesteps(run.train_steps), run.form.scheduler("ddpm")
    val = run.source.val_items(run.spps, d.val_frames) if run.rank == 0 else []
    net = run.model
    if run.world > 1:
        from torch.nn.parallel import DistributedDataParallel as DDP
        net = DDP(run.model, device_ids=[run.device.index] if run.device.type == "cuda" else None)
    if run.says:
        print(f"{run.name}: OIDN base ({run.base_what}), {len(crops.frames)} train frames at {run.spps} "
              f"spp, {len(val)} validation images, {steps_per_epoch} steps per epoch; ready in "
              f"{time.perf_counter() - t:.1f} s", flush=True)
    return Data(crops, val, per_rank, steps_per_epoch, steps_per_epoch * d.epochs, focus, noise, net)


def epoch_batches(run: Run, data: Data, epoch: int) -> DataLoader:
    """This rank's batches of the epoch (a permutation of the crops by seed and epoch); the model in training mode."""
    data.crops.set_epoch(epoch)
    order = np.random.default_rng([run.cfg.seed, epoch]).permutation(len(data.crops))
    mine = order[run.rank::run.world][: data.per_rank].tolist()
    run.model.train()
    # Items come from default_rng([seed, epoch, index]): the batches are the same with any number of workers.
    return DataLoader(data.crops, batch_size=run.cfg.diffusion.batch_size, sampler=mine, drop_last=True,
                      num_workers=run.cfg.diffusion.loader_workers, pin_memory=run.device.type == "cuda")


def validate_start(run: Run, val: list[dict], history: list) -> dict | None:
    """Epoch 0: the untrained model's validation, saved as the best so far; the best (None without val frames)."""
    entry = {"epoch": 0, "train_loss": None, "terms": {}, "skipped_steps": 0, "lr": 0.0,
             "val": validate(run.model, val, run.form, run.cfg.seed), "seconds": 0.0}
    if entry["val"] is None:
        return None
    history.append(entry)
    save_epoch(run, run.folder, entry)
    return {"epoch": 0, "score": entry["val"]["psnr"], "val": entry["val"], "train_loss": None}


def end_epoch(run: Run, val: list[dict], entry: dict, history: list, best: dict | None, t_start: float) -> dict | None:
    """Rank 0 after an epoch: validation with the EMA weights, the best checkpoint and the ``keep_epochs`` folders,
    the history files, then ``last.safetensors``, written last: it is the commit point of the epoch, so a kill
    before it reruns the epoch (same result) and rewrites the files above. The new best."""
    with ema_weights(run.ema, run.model.control):
        entry["val"] = validate(run.model, val, run.form, run.cfg.seed)
        entry["seconds"] = round(time.perf_counter() - t_start, 2)
        history.append(entry)
        score = entry["val"]["psnr"] if entry["val"] else None
        if score is not None and (best is None or score > best["score"]):
            best = {"epoch": entry["epoch"], "score": score, "val": entry["val"], "train_loss": entry["train_loss"]}
            save_epoch(run, run.folder, entry)
        # Chosen epochs' weights beside the best (chosen on this run's val frames alone): to score on other scenes.
        if entry["epoch"] in run.cfg.diffusion.keep_epochs:
            save_epoch(run, run.folder / f"epoch{entry['epoch']}", entry)
    write_history(run, history, best)
    fields, tensors = ({}, None) if run.ema is None else (
        {"ema_step": run.ema.optimization_step}, {f"ema.{i}": p for i, p in enumerate(run.ema.shadow_params)})
    save_last(run.folder / "last.safetensors", run.model.control, run.opt,
              {"epoch": entry["epoch"], "history": history, "best": best, "fingerprint": run.fingerprint, **fields},
              FORMAT, extra=tensors)
    return best


def calibrate_sigma(run: Run, val: list[dict]) -> None:
    """σ calibrated on the validation frames with the best weights (``train.infer.calibrate``), into model.json."""
    path = run.folder / "model.json"
    if run.rank != 0 or not val or not path.exists():
        return
    # Imported here: inference is not needed before the training is done (nor loaded before the first step).
    from .infer import calibrate, load_denoiser
    record = read_json(path, "model record")
    sg = calibrate(load_denoiser(run.folder, str(run.device)), val, run.cfg.seed)
    fitted = f"σ scale {sg['scale']:.3g} fitted on {sg['pixels']} validation pixels ({sg['steps']} steps, " \
             f"{sg['samples']} samples)"
    if sg["pixels"] > 0 and not SIGMA_PLAUSIBLE[0] <= sg["scale"] <= SIGMA_PLAUSIBLE[1]:
        # a fit this far off says the samples' spread does not track the error here: no σ rather than a wrong one
        record.pop("sigma", None)
        atomic_write_json(path, record)
        print(f"{run.name}: the σ fit failed: {fitted}, outside {SIGMA_PLAUSIBLE[0]:g}..{SIGMA_PLAUSIBLE[1]:g}; "
              "model.json keeps no σ scale (the std layer is the samples' unscaled spread)", flush=True)
        return
    record["sigma"] = sg
    atomic_write_json(path, record)
    if run.says:
        print(f"{run.name}: {fitted}", flush=True)


# ---- validation, files and lines ---------------------------------------------------------------------


def validate(model: ControlledOIDN, items: list[dict], form: Formulation, seed: int) -> dict | None:
    """The sampler's PSNR on the val frames, OIDN's (the estimate's) and the gain per spp (None without frames)."""
    if not items:
        return None
    model.eval()
    rows, device = [], next(model.parameters()).device
    for it in items:
        x, cond = it["x"].to(device), it["cond"].to(device)
        mean, _, est = sample(model, x, cond, form, seed=seed)
        H, W = it["ref"].shape[:2]
        out = network_output(mean, it["scale"], (H, W))[0].permute(1, 2, 0).cpu().numpy()
        stock = network_output(est, it["scale"], (H, W))[0].permute(1, 2, 0).cpu().numpy()
        rows.append((it["spp"], min(psnr(out, it["ref"]), PSNR_CEILING), min(psnr(stock, it["ref"]), PSNR_CEILING)))
    model.train()
    out = {"psnr": float(np.mean([r[1] for r in rows])), "estimate_psnr": float(np.mean([r[2] for r in rows])),
           "images": len(rows), "steps": form.steps}
    for spp in sorted({r[0] for r in rows}):
        out[f"gain_spp{spp}"] = float(np.mean([r[1] - r[2] for r in rows if r[0] == spp]))
    return out


def save_epoch(run: Run, folder: Path, entry: dict) -> None:
    """The model in place (the EMA weights inside ``ema_weights``) as a model folder, with the epoch's record."""
    save(folder, run.model, run.blob, run.base_what, run.network, run.form, run.spps,
         {"epoch": entry["epoch"], "metrics": entry["val"], "train_loss": entry["train_loss"],
          "store": str(run.cfg.store), "settings": run.fingerprint, **run.kept,
          # how far the base is from OIDN (what fine-tuning changed, WiSE-FT), where known: export --base-blend
          **({} if run.base_blend is None else {"base_blend": float(run.base_blend)})})


def write_history(run: Run, history: list, best: dict | None) -> None:
    """train.json (the epochs, the best, the machine) and loss.png (the train loss, the val gain over OIDN)."""
    # Imported here: not needed before the first step.
    from mcdenoise.pipeline.figures import plot_curves
    atomic_write_json(run.folder / "train.json", {"name": run.name, "history": history, "best": best,
                                                  "machine": run_machine(run.device, run.world)})
    curves = {"train loss": [(h["epoch"], h["train_loss"]) for h in history if h["train_loss"] is not None]}
    gain = {"val PSNR - OIDN (dB)": [(h["epoch"], h["val"]["psnr"] - h["val"]["estimate_psnr"])
                                    for h in history if h.get("val")]}
    plot_curves(run.folder / "loss.png", curves, f"Control Module on OIDN ({run.cfg.store})", right=gain,
                right_label="dB")


def epoch_entry(epoch: int, kept: list[dict], skipped: int, lr: float) -> dict:
    """The history entry of an epoch from the terms of its finite steps (``val`` and ``seconds`` come after)."""
    mean = {k: float(np.mean([t[k] for t in kept])) for k in (kept[0] if kept else {})}
    return {"epoch": epoch + 1, "train_loss": mean.pop("loss", None), "terms": mean, "steps": len(kept) + skipped,
            "skipped_steps": skipped, "lr": lr}


def nan_message(name: str, in_row: int, epoch: int, step: int) -> str:
    return (f"{name}: {in_row} steps in a row had a non-finite loss or gradient (epoch {epoch + 1}, step {step}); "
            "check the data (python -m pipeline inspect) or lower the learning rate")


def epoch_line(name: str, entry: dict) -> str:
    v, loss = entry["val"], entry["train_loss"]
    line = f"{name} epoch {entry['epoch']}: loss " + ("n/a" if loss is None else f"{loss:.4f}")
    line += "".join(f", {k} {x:.4f}" for k, x in entry.get("terms", {}).items())
    if v:
        gains = " ".join(f"{k[8:]} {v[k]:+.3f}" for k in v if k.startswith("gain_spp"))
        line += f"; val PSNR {v['psnr']:.3f} dB (OIDN {v['estimate_psnr']:.3f}; gain by spp: {gains})"
    return line


def summarize(run: Run, history: list, best: dict | None, trained: int, seconds: float) -> dict:
    epochs = history[-1]["epoch"] if history else 0
    line = f"{run.name}: {epochs} epochs ({trained} this run, {seconds:.1f} s)"
    if best:
        v = best["val"]
        line += f"; best epoch {best['epoch']}" + (f": val PSNR {v['psnr']:.3f} dB, "
                                                  f"{v['psnr'] - v['estimate_psnr']:+.3f} dB over OIDN" if v else "")
    line += f" -> {run.folder / 'control.safetensors'}"
    return {"folder": str(run.folder), "epochs": epochs, "trained_epochs": trained, "best": best, "seconds": seconds,
            "line": line}


# ---- learning rate, EMA, DDP, precision ------------------------------------------------------------


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


def run_machine(device: torch.device, world: int = 1) -> dict:
    """What a run trained on, for its model card: the machine, torch, the device and the ranks."""
    # Imported here: not needed before the first step.
    from mcdenoise.pipeline.versions import machine
    return {**machine(), "torch": torch.__version__, "device": str(device), "ranks": world}


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
