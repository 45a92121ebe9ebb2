"""The training task: the Control Module on OIDN's frozen network, trained on a config's store.

    make train SPP=any      → python -m pipeline train --model diffusion --spp any → train(cfg, "any")
                            → runs/<config>/diffusion_sppany[_<name>]/

``train`` runs ``RefineTask`` under ``clean.fit`` (epochs, the time budget, resuming, the best
checkpoint). The task reads top to bottom: the model (``train.model``: OIDN frozen, a new Control
Module or a trained one to warm-start from), the data (``train.data``: the store's pack, crops with
OIDN's augmentation and buffer-group dropout, the val frames), the optimiser (AdamW on the Control
Module only, warm-up and cosine decay, an EMA of its weights); then the step, inline: the residual
around the base's output is noised at a t drawn with ``t_focus`` on the sampler's steps
(``train.sampler``), the network predicts x̂₀, the loss is each crop's error relative to OIDN's
(``train.loss``), weighted by min-SNR; then validation (``train.sampler``, PSNR against the base's)
and the files. DDP under torchrun. The run folder: ``control.safetensors`` (the Control Module, EMA),
``base.tza`` (the frozen base's float16 weights, so the run is self-contained), ``model.json``,
``last.safetensors``, ``train.json``, ``loss.png``, and ``epoch<N>/`` for each of ``diffusion.keep_epochs``
(model folders of those epochs' EMA weights); σ is fitted at the end (``train.infer.calibrate``).
"""
from __future__ import annotations

import contextlib
import hashlib
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from mcdenoise.clean.fit import NanGuard, Task, apply_update, fit
from mcdenoise.pipeline import config as config_mod, weights
from mcdenoise.pipeline.config import Config, pick_device
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.exr import atomic_write_json, read_json
from mcdenoise.pipeline.figures import plot_curves
from mcdenoise.pipeline.metrics import PSNR_CEILING, psnr
from mcdenoise.pipeline.store import sha256
from mcdenoise.pipeline.versions import machine
from mcdenoise.pipeline.weights import read_tza

from . import oidn
from .data import Crops, StoreSource
from .infer import calibrate, load_denoiser
from .loss import relative_loss
from .model import FORMAT, NETWORK, ControlledOIDN, UNet, cond_names, load, network_output, run_dir, save
from .sampler import Formulation, sample, snr_weight


def train(cfg: Config, spp="any", quiet: bool = False) -> dict:
    """Train (or resume) the Control Module on OIDN; ``clean.fit``'s summary."""
    try:
        return fit(RefineTask(cfg, spp, quiet), quiet=quiet)
    finally:
        dist_shutdown()


# What a warm-started run copies from its start's model.json besides the weights: how the model is used
KEPT = ("control_without_groups",)


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


# ---- the base of a new run --------------------------------------------------------------------


def base_blob(cfg: Config) -> tuple[bytes, str]:
    """(the base's float16 TZA blob, what it is): ``diffusion.base`` 'oidn' (OIDN's ``diffusion.base_network``,
    from ``oidn.weights`` or pyoidn), 'oidn_ft' (this config's oidn_ft run of that network, as exported) or a
    .tza file of it."""
    base, network = cfg.diffusion.base, cfg.diffusion.base_network
    if base == "oidn":
        return oidn.weights_blob(network, oidn.weights_source(network, cfg.oidn.weights)), f"OIDN {network}"
    if base == "oidn_ft":
        from .baselines.oidn_ft import export_blob, load_run
        folder = config_mod.run_dir(cfg, "oidn_ft", variant=network)
        return export_blob(load_run(folder, cfg)[0]), f"oidn_ft run {folder} (blend {cfg.oidn_ft.blend:g})"
    return oidn.weights_blob(network, base), str(base)



# ---- the training run --------------------------------------------------------------------------


class RefineTask(Task):
    """The Control Module on OIDN, trained on the store's train split (see the module docstring)."""

    minimize = False          # validation PSNR
    validate_initial = True   # epoch 0 is OIDN exactly: the run must beat it to keep anything

    def __init__(self, cfg: Config, spp="any", quiet: bool = False, folder: Path | None = None,
                 init: Path | None = None):
        """The config's store (``StoreSource``) trains and validates; ``folder``: the run folder (default
        ``<runs>/diffusion_spp<N>[_name]``); ``init``: a trained model folder whose base and Control Module the run
        starts from (default ``diffusion.init``; else OIDN and a new one)."""
        d = self.d = cfg.diffusion
        self.cfg, self.quiet = cfg, quiet
        init = init or (Path(d.init) if d.init else None)
        # the base's network: a warm start keeps its model's
        self.network = (weights.read_record(init, "oidn_control", "").get("base_network", NETWORK) if init is not None
                        else d.base_network)
        self.source = StoreSource(cfg, self.network)
        self.spps = self.source.spps(spp)
        self.rank, self.world = dist_info()
        self.folder = folder or run_dir(cfg, spp)
        self.name, self.epochs, self.time_budget_s, self.nan_limit = self.folder.name, d.epochs, d.time_budget_s, d.nan_limit
        self.device = pick_device(d.device)
        self.autocast = autocast_dtype(d.precision, self.device)

        # The model: OIDN frozen (its float16 blob kept with the run) and a new Control Module, or both
        # from a trained model folder (``init`` / diffusion.init: a warm start).
        form, self.train_steps, self.kept = Formulation.from_config(d), list(d.train_steps), {}
        if init is not None:
            start, meta = load(init, self.device)
            self.blob, self.base_what = (Path(init) / meta["base"]).read_bytes(), f"{init}/{meta['base']}"
            self.base_blend = meta.get("base_blend")
            form, self.train_steps, differ = warm_start_recipe(d, meta)
            self.kept = {k: meta[k] for k in KEPT if k in meta}
            if differ and not quiet and self.rank == 0:
                print(f"diffusion.init={init}: the run keeps that model's formulation; not used: {'; '.join(differ)}",
                      flush=True)
        else:
            self.blob, self.base_what = base_blob(cfg)
            self.base_blend = {"oidn": 0.0, "oidn_ft": cfg.oidn_ft.blend}.get(cfg.diffusion.base)
        self.form = form
        torch.manual_seed(cfg.seed)
        base = UNet.from_tza(read_tza(self.blob, self.base_what))
        self.model = ControlledOIDN(base, len(cond_names())).to(self.device)
        if init is not None:
            self.model.control.load_state_dict(start.control.state_dict())
        self.state = self.model.control
        self.params = self.model.trainable_parameters()
        self.optimizers = torch.optim.AdamW(self.params, lr=d.lr, weight_decay=d.weight_decay)
        self.ema = make_ema(self.state, d.ema)
        self.fmt = FORMAT
        self.fingerprint = {"spp": str(spp), "seed": cfg.seed, "base_sha256": hashlib.sha256(self.blob).hexdigest(),
                            # the start by content, not only by path: a replaced folder must not resume this run
                            **({"init": str(init), "init_sha256": sha256(Path(init) / "control.safetensors")}
                               if init is not None else {}),
                            "formulation": self.form.record(), "train_steps": self.train_steps,
                            **{k: getattr(d, k) for k in ("crop", "batch_size", "crops_per_frame", "epoch_steps", "lr",
                                                           "weight_decay", "warmup_steps", "grad_clip", "ema", "epochs",
                                                           "hdr_weight", "dropout")}}
        self.output = str(self.folder / "control.safetensors")

    # ---- data
    def prepare(self) -> None:
        t = time.perf_counter()
        pack = self.source.train_pack(self.quiet or self.rank > 0)
        self.crops = Crops(pack, self.d.crop, self.d.crops_per_frame, self.cfg.seed, self.spps, dropout=self.d.dropout)
        self.per_rank = len(self.crops) // self.world
        self.steps_per_epoch = max(1, self.per_rank // self.d.batch_size)
        if self.d.epoch_steps:
            self.steps_per_epoch = min(self.steps_per_epoch, self.d.epoch_steps)
            self.per_rank = min(self.per_rank, self.steps_per_epoch * self.d.batch_size)
        self.total_steps = self.steps_per_epoch * self.d.epochs
        self.focus = self.form.train_timesteps(self.train_steps)
        self.noise_sched = self.form.scheduler("ddpm")
        self.val = self.source.val_items(self.spps, self.d.val_frames) if self.rank == 0 else []
        self.net = self.model
        if self.world > 1:
            from torch.nn.parallel import DistributedDataParallel as DDP
            self.net = DDP(self.model, device_ids=[self.device.index] if self.device.type == "cuda" else None)
        self._guard = NanGuard(self.name, self.nan_limit, TrainError)
        if not self.quiet and self.rank == 0:
            print(f"{self.name}: OIDN base ({self.base_what}), {len(self.crops.frames)} train frames at {self.spps} "
                  f"spp, {len(self.val)} validation images, {self.steps_per_epoch} steps per epoch; ready in "
                  f"{time.perf_counter() - t:.1f} s", flush=True)

    def guard(self) -> NanGuard:
        return self._guard

    def batches(self, epoch: int):
        self.crops.set_epoch(epoch)
        order = np.random.default_rng([self.cfg.seed, epoch]).permutation(len(self.crops))
        mine = order[self.rank::self.world][: self.per_rank].tolist()
        self.model.train()
        # Items come from default_rng([seed, epoch, index]): the batches are the same with any number of workers.
        return DataLoader(self.crops, batch_size=self.d.batch_size, sampler=mine, drop_last=True,
                          num_workers=self.d.loader_workers, pin_memory=self.device.type == "cuda")

    # ---- the step
    def step(self, batch: dict, epoch: int, index: int) -> tuple[dict, bool]:
        gen = torch.Generator().manual_seed(int(np.random.default_rng([self.cfg.seed, epoch, index, self.rank])
                                                .integers(2 ** 62)))
        for g in self.optimizers.param_groups:
            g["lr"] = self.d.lr * lr_factor(epoch * self.steps_per_epoch + index, self.total_steps, self.d.warmup_steps)
        x, cond, target, scale = batch["x"], batch["cond"], batch["target"], batch["scale"]
        feats, est = self.model.estimate(x)
        y = (target - est) / self.form.residual_scale
        t = self.form.draw_t(x.shape[0], self.focus, gen).to(self.device)
        z = self.noise_sched.add_noise(y, torch.randn(y.shape, generator=gen).to(self.device), t)
        with torch.autocast(self.device.type, dtype=self.autocast, enabled=self.autocast is not None):
            out, _ = self.net(x, cond, z, t, base=(feats, est))
        per_crop, terms = relative_loss(out.float(), est, target, scale, self.d.hdr_weight)
        w = snr_weight(self.noise_sched, t, self.form.snr_gamma, self.form.snr_floor).to(self.device)
        loss = (w * per_crop).mean()
        ok = apply_update(loss, self.optimizers, self.params, self.d.grad_clip)
        if ok and self.ema is not None:
            self.ema.step(self.state.parameters())
        return {"loss": float(loss.detach()), **{k: float(v) for k, v in terms.items()}}, ok

    def entry(self, epoch: int, kept: list[dict], skipped: int) -> dict:
        mean = {k: float(np.mean([t[k] for t in kept])) for k in (kept[0] if kept else {})}
        return {"epoch": epoch + 1, "train_loss": mean.pop("loss", None), "terms": mean, "steps": len(kept) + skipped,
                "skipped_steps": skipped,
                "lr": self.optimizers.param_groups[0]["lr"]}

    def initial_entry(self) -> dict:
        return {"epoch": 0, "train_loss": None, "terms": {}, "skipped_steps": 0, "lr": 0.0}

    # ---- validation and files
    def validate(self) -> dict | None:
        if not self.val:
            return None
        self.model.eval()
        rows = []
        for it in self.val:
            x, cond = it["x"].to(self.device), it["cond"].to(self.device)
            mean, _, est = sample(self.model, x, cond, self.form, seed=self.cfg.seed)
            H, W = it["ref"].shape[:2]
            out = network_output(mean, it["scale"], (H, W))[0].permute(1, 2, 0).cpu().numpy()
            stock = network_output(est, it["scale"], (H, W))[0].permute(1, 2, 0).cpu().numpy()
            rows.append((it["spp"], min(psnr(out, it["ref"]), PSNR_CEILING), min(psnr(stock, it["ref"]), PSNR_CEILING)))
        self.model.train()
        out = {"psnr": float(np.mean([r[1] for r in rows])), "estimate_psnr": float(np.mean([r[2] for r in rows])),
               "images": len(rows), "steps": self.form.steps}
        for spp in sorted({r[0] for r in rows}):
            out[f"gain_spp{spp}"] = float(np.mean([r[1] - r[2] for r in rows if r[0] == spp]))
        return out

    def evaluation(self):
        return ema_weights(self.ema, self.state)

    def score(self, entry: dict) -> float | None:
        return entry["val"]["psnr"] if entry["val"] else None

    def save_best(self, entry: dict) -> None:
        self.save_epoch(self.folder, entry)

    def keep(self, entry: dict) -> None:
        """The EMA Control Module of the epochs in ``diffusion.keep_epochs``, each a model folder
        ``<run>/epoch<N>``: for scoring on other scenes than the run's validation frames."""
        if entry["epoch"] in self.d.keep_epochs:
            self.save_epoch(self.folder / f"epoch{entry['epoch']}", entry)

    def save_epoch(self, folder: Path, entry: dict) -> None:
        """The model in place (the EMA weights under ``evaluation``) as a model folder, with the epoch's record."""
        save(folder, self.model, self.blob, self.base_what, self.network, self.form, self.spps,
             {"epoch": entry["epoch"], "metrics": entry["val"], "train_loss": entry["train_loss"],
              "store": str(self.cfg.store), "settings": self.fingerprint, **self.kept,
              # how far the base is from OIDN (what fine-tuning changed, WiSE-FT), where known: export --base-blend
              **({} if self.base_blend is None else {"base_blend": float(self.base_blend)})})

    def write_history(self, history: list, best: dict | None) -> None:
        atomic_write_json(self.folder / "train.json", {"name": self.name, "history": history, "best": best,
                                                       "machine": run_machine(self.device, self.world)})
        curves = {"train loss": [(h["epoch"], h["train_loss"]) for h in history if h["train_loss"] is not None]}
        gain = {"val PSNR - OIDN (dB)": [(h["epoch"], h["val"]["psnr"] - h["val"]["estimate_psnr"])
                                        for h in history if h.get("val")]}
        plot_curves(self.folder / "loss.png", curves, f"Control Module on OIDN ({self.cfg.store})", right=gain,
                    right_label="dB")

    def resume(self, record: dict, extra: dict) -> None:
        if self.ema is not None:
            self.ema.shadow_params = [extra[f"ema.{i}"].to(self.device) for i in range(len(self.ema.shadow_params))]
            self.ema.optimization_step = int(record["ema_step"])

    def checkpoint(self) -> tuple[dict, dict | None]:
        if self.ema is None:
            return {}, None
        return {"ema_step": self.ema.optimization_step}, {f"ema.{i}": p for i, p in enumerate(self.ema.shadow_params)}

    def when_done(self, history: list, best: dict | None) -> None:
        if history:
            self.write_history(history, best)

    def finish(self) -> None:
        """σ calibrated on the validation frames with the best weights (``calibrate``), into model.json."""
        if self.rank == 0 and self.val and (self.folder / "model.json").exists():
            record = read_json(self.folder / "model.json", "model record")
            record["sigma"] = calibrate(load_denoiser(self.folder, str(self.device)), self.val, self.cfg.seed)
            atomic_write_json(self.folder / "model.json", record)
            if not self.quiet:
                sg = record["sigma"]
                print(f"{self.name}: σ scale {sg['scale']:.3g} fitted on {sg['pixels']} validation pixels "
                      f"({sg['steps']} steps, {sg['samples']} samples)", flush=True)

    def epoch_line(self, entry: dict) -> str:
        v, loss = entry["val"], entry["train_loss"]
        line = f"{self.name} epoch {entry['epoch']}: loss " + ("n/a" if loss is None else f"{loss:.4f}")
        line += "".join(f", {k} {x:.4f}" for k, x in entry.get("terms", {}).items())
        if v:
            gains = " ".join(f"{k[8:]} {v[k]:+.3f}" for k in v if k.startswith("gain_spp"))
            line += f"; val PSNR {v['psnr']:.3f} dB (OIDN {v['estimate_psnr']:.3f}; gain by spp: {gains})"
        return line

    def best_text(self, best: dict) -> str:
        v = best["val"]
        return (f"best epoch {best['epoch']}" + (f": val PSNR {v['psnr']:.3f} dB, {v['psnr'] - v['estimate_psnr']:+.3f} "
                                                 "dB over OIDN" if v else ""))


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
