"""The diffusion denoiser's training run on the IF-II-layout base, and what every diffusion run shares.

    python -m pipeline train --model diffusion --spp 4|any      (make train SPP=4)  -> ControlTask(cfg, spp)
    torchrun --nproc_per_node 2 -m pipeline train --model diffusion --spp 4

``ControlTask`` is a ``pipeline.fit`` task (the loop: resume, best and last checkpoints, time budget,
summary) and reads top to bottom: the model (the base of ``diffusion.base``, or a new one, and a new
Control Module), the data (the store's train split, from the pack or its EXRs), the optimiser and
the EMA; then the step; then the validation score and the files. Per step:

    x = GT_clean crop, x_est = the first estimate, F = condition, t (``Formulation.draw_t``), ε ~ N(0, I)
    refine: y = (x − x_est)/s, z_t = add_noise(y, ε, t), loss = w(t) · MSE(ŷ, y) / (the crop's own error)
    paper:  z_t = q_sample(x, t, ε), loss = ‖ε − ε̂‖² + L_t(Σ_θ)                (``train.diffusion``)

AdamW on the trainable parameters, linear warm-up then cosine decay (a pure function of the step,
so nothing to restore), gradient clipping, bf16 autocast on CUDA, an EMA of the trained weights
(what validation scores and the run saves). A step whose loss or gradient norm is not finite is
skipped and counted over the whole run; ``nan_limit`` in a row stop it. Every random draw comes
from generators seeded by (seed, epoch, step, rank) and the epoch's crops from
``default_rng([seed, epoch, item])``: a resumed run continues exactly as the uninterrupted one.
``train.pretrain.PretrainTask`` is the same run with the base as the trained module and
restoration pairs as data. ``lr_factor``, ``make_ema``, ``ema_weights`` and the DDP helpers serve
the OIDN-based run (``train.oidn_refine``) too.

Under ``torchrun`` (DDP; gloo on CPU, NCCL on GPU) each rank takes every world-th item of the
epoch's permutation; rank 0 validates and writes; at the end the ranks compare a checksum of
their weights and fail loudly if they diverged.
"""
from __future__ import annotations

import contextlib
import math
import os

import numpy as np
import torch
from torch.utils.data import DataLoader

from mcdenoise.pipeline.checkpoint import NanGuard, plot_curves
from mcdenoise.pipeline.config import PAPER_STEPS, Config
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.exr import atomic_write_json
from mcdenoise.pipeline.fit import Task, apply_update, fit
from mcdenoise.pipeline.metrics import PSNR_CEILING, psnr
from mcdenoise.pipeline.runs import pick_device
from mcdenoise.pipeline.store import Store
from mcdenoise.pipeline.versions import machine

from . import diffusion
from .data import DenoisePairs, from_model
from .formulation import Formulation
from .model import FORMAT, base_sha256, build, estimator_and_id, new_base, run_dir, save
from .pack import PackPairs, ensure_pack, pack_path
from .sampler import sample


def train(cfg: Config, spp, quiet: bool = False) -> dict:
    """Train (or resume) the Control Module for ``spp`` (or 'any'); the summary of ``pipeline.fit``."""
    try:
        return fit(ControlTask(cfg, spp, quiet), quiet=quiet)
    finally:
        dist_shutdown()


class ControlTask(Task):
    """The Control Module (and the base, with ``diffusion.train_base``) trained from the store's low-spp
    stacks to GT_clean. ``data``: a data set given instead of the store's train split (items noisy, aux,
    target[, image]; ``set_epoch``); then nothing is validated.

    What the shared methods below read, set by ``__init__`` (and by ``PretrainTask``'s): ``cfg``,
    ``model``, ``state`` (the saved module), ``params``, ``data``, ``val`` (validation items or None),
    ``objective``, ``optimizers``, ``ema``, ``s`` (epochs, batch_size, lr, weight_decay, time_budget_s),
    ``warmup_steps``, ``grad_clip``, ``epoch_steps``, ``title``, and ``pipeline.fit.Task``'s attributes."""

    minimize = False
    fmt = FORMAT

    def __init__(self, cfg: Config, spp="any", quiet: bool = False, data=None):
        f = self.s = cfg.diffusion
        self.cfg, self.spp, self.quiet = cfg, spp, quiet
        store, choices = (None, []) if data is not None else _training_store(cfg, spp)
        if not f.control and not f.train_base:
            raise TrainError("diffusion.control=false with train_base=false leaves nothing to train; the base-only "
                             "ablation needs no training (the evaluator runs it from the base)")
        self.rank, self.world = dist_info()
        self.device = pick_device(f.device)
        self.autocast = autocast_dtype(f.precision, self.device)
        self.folder = run_dir(cfg, spp)
        self.name, self.epochs, self.time_budget_s, self.nan_limit = self.folder.name, f.epochs, f.time_budget_s, f.nan_limit
        self.warmup_steps, self.grad_clip, self.epoch_steps = f.warmup_steps, f.grad_clip, f.epoch_steps
        self.title = f"Control Module, {spp} spp -> GT_clean"
        form = self.form = Formulation.from_config(f)

        # The model: the base (a new one is written into the run folder first) and a new Control Module.
        new_base(cfg, self.folder)
        self.model = build(cfg, run=self.folder).to(self.device)
        self.state = torch.nn.ModuleDict({k: m for k, m in (("control", self.model.control),
                                                            ("base", self.model.base if f.train_base else None)) if m})
        self.params = self.model.trainable_parameters()

        # The data: crops of the train split (from the pack, decoded once), the first val frames whole.
        crop = f.crop if store is None else fit_crop(f.crop, frame_sides(store), self.model.multiple)
        if data is not None:
            self.data, self.val = data, None
        elif f.pack:
            est, est_id = estimator_and_id(cfg)
            path = ensure_pack(store, store.frames_with("train"), pack_path(cfg.runs, "train", form.estimate),
                               f.tonemap, est, quiet, est_id)
            self.data = PackPairs(path, crop, f.crops_per_frame, cfg.seed, choices, f.tonemap, form.estimate)
            choices = sorted(set(self.data.t["spp"].tolist()) & set(choices))
        else:
            self.data = DenoisePairs(store, store.frames_with("train"), choices, crop, f.crops_per_frame, cfg.seed,
                                     f.tonemap, estimator=estimator_and_id(cfg)[0])
        if store is not None:
            self.val = validation_items(cfg, store, store.frames_with("val"), choices)

        # The optimiser, the EMA and the settings a resume must share.
        self.objective = diffusion.objective(self.device) if form.paper else form.objective(list(f.train_steps))
        self.validate_initial = not form.paper   # the untrained refine model is its first estimate exactly
        self.optimizers = torch.optim.AdamW(self.params, lr=f.lr, weight_decay=f.weight_decay)
        self.ema = make_ema(self.state, f.ema)
        self.fingerprint = {"spp": str(spp), "seed": cfg.seed, "base_sha256": base_sha256(cfg, self.folder),
                            "crop": crop, "formulation": form.record(), "train_steps": list(f.train_steps), "ema": f.ema,
                            **{k: getattr(f, k) for k in ("tonemap", "batch_size", "crops_per_frame", "lr",
                                                           "weight_decay", "warmup_steps", "grad_clip", "train_base",
                                                           "control", "epochs")},
                            # only when set, so runs from before the key resume as they were
                            **({"epoch_steps": f.epoch_steps} if f.epoch_steps else {})}

    # ---- the epoch's batches: rank r takes every world-th item of the permutation, at most epoch_steps batches
    def prepare(self) -> None:
        self.net = self.model
        if self.world > 1:
            from torch.nn.parallel import DistributedDataParallel as DDP
            self.net = DDP(self.model, device_ids=[self.device.index] if self.device.type == "cuda" else None)
        self.per_rank = len(self.data) // self.world
        self.steps_per_epoch = max(1, self.per_rank // self.s.batch_size)
        if self.epoch_steps > 0:   # a subset per epoch: validation, checkpoint and budget come more often
            self.steps_per_epoch = min(self.steps_per_epoch, self.epoch_steps)
            self.per_rank = min(self.per_rank, self.steps_per_epoch * self.s.batch_size)
        self.total_steps = self.s.epochs * self.steps_per_epoch
        self._guard = NanGuard(self.name, self.nan_limit, TrainError)   # one for the whole run

    def guard(self) -> NanGuard:
        return self._guard

    def batches(self, epoch: int):
        self.data.set_epoch(epoch)
        order = np.random.default_rng([self.cfg.seed, epoch]).permutation(len(self.data))
        mine = order[self.rank::self.world][:self.per_rank].tolist()
        self.model.train()
        return DataLoader(self.data, batch_size=self.s.batch_size, sampler=mine, drop_last=True, num_workers=0)

    # ---- the step
    def step(self, batch: dict, epoch: int, index: int) -> tuple[dict, bool]:
        """The learning rate of this step, the objective's loss, clipped gradients, AdamW and the EMA; a
        non-finite loss or gradient norm changes nothing."""
        gen = torch.Generator().manual_seed(
            int(np.random.default_rng([self.cfg.seed, epoch, index, self.rank]).integers(2**62)))
        for g in self.optimizers.param_groups:
            g["lr"] = self.s.lr * lr_factor(epoch * self.steps_per_epoch + index, self.total_steps, self.warmup_steps)
        loss, terms = self.objective(self.net, batch, gen, self.device, self.autocast)
        if not apply_update(loss, self.optimizers, self.params, self.grad_clip):
            return {}, False
        if self.ema is not None:
            self.ema.step(self.state.parameters())
        return {"loss": float(loss.detach()), "mse": float(terms["mse"]), "vb": float(terms["vb"])}, True

    def entry(self, epoch: int, kept: list[dict], skipped: int) -> dict:
        """Mean loss and its terms over the epoch's finite steps (nan / None without any)."""
        mean = {k: float(np.mean([t[k] for t in kept])) if kept else None for k in ("loss", "mse", "vb")}
        return {"epoch": epoch + 1, "train_loss": float("nan") if mean["loss"] is None else mean["loss"],
                "mse": mean["mse"], "vb": mean["vb"], "skipped_steps": skipped,
                "lr": self.optimizers.param_groups[0]["lr"]}

    def initial_entry(self) -> dict:
        return {"epoch": 0, "train_loss": None, "mse": None, "vb": None, "skipped_steps": 0, "lr": 0.0}

    # ---- validation: PSNR (x/(1+x)) of the configured sampler, beside the noisy input's and the estimate's
    def validate(self) -> dict | None:
        if not self.val:
            return None
        f, form = self.cfg.diffusion, self.form
        skip = f.val_skip if form.paper else f.skip
        self.model.eval()
        outs = []
        for it in self.val["items"]:
            noisy, aux, image = (it[k][None].to(self.device) for k in ("noisy", "aux", "image"))
            out = sample(self.model, noisy, aux, image=image, formulation=form, skip=skip, seed=self.cfg.seed,
                         threshold_ratio=f.threshold_ratio, autocast_dtype=self.autocast, variance=f.variance)
            outs.append(out[0].float().cpu())
        self.model.train()
        return {"psnr": self.val["score"](outs), **self.val["base"], "skip": skip,
                "steps": PAPER_STEPS if form.paper else f.steps}

    def evaluation(self):
        return ema_weights(self.ema, self.state)   # validated and saved: the EMA of the weights, if any

    def score(self, entry: dict) -> float:
        """Higher is better: validation PSNR, else minus the training loss."""
        return entry["val"]["psnr"] if entry["val"] else -entry["train_loss"]

    # ---- files
    def save_best(self, entry: dict) -> None:
        save(self.folder, self.model, self.cfg, str(self.spp),
             {"epoch": entry["epoch"], "metrics": entry["val"], "train_loss": entry["train_loss"]})

    def write_history(self, history: list, best: dict | None) -> None:
        plot_history(self.folder / "loss.png", history, self.title or self.name)
        atomic_write_json(self.folder / "train.json", {"name": self.name, "history": history, "best": best,
                                                       "machine": run_machine(self.device, self.world)})

    def checkpoint(self) -> tuple[dict, dict | None]:
        if self.ema is None:
            return {}, None
        return ({"ema_step": self.ema.optimization_step},
                {f"ema.{i}": p for i, p in enumerate(self.ema.shadow_params)})

    def resume(self, record: dict, extra: dict) -> None:
        if self.ema is not None:
            self.ema.shadow_params = [extra[f"ema.{i}"].to(self.device) for i in range(len(self.ema.shadow_params))]
            self.ema.optimization_step = int(record["ema_step"])

    def finish(self) -> None:
        if self.world > 1:
            _check_in_sync(self.state, self.world)

    # ---- report
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
        return {"name": self.name, **({"skipped_steps": self._guard.skipped} if hasattr(self, "_guard") else {})}


# ---- the data's pieces ---------------------------------------------------------------------------


def _training_store(cfg: Config, spp) -> tuple[Store, list[int]]:
    """The config's store and the sample counts a run for ``spp`` trains on; a clear error without frames."""
    store = Store(cfg.store)
    store.training_frames()
    return store, store.spp_choices(spp)


def frame_sides(store: Store) -> list[int]:
    """The shorter side of each train scene's frames."""
    return [min(store.scene_manifest(s)["resolution"]) for s in {k.scene for k in store.frames_with("train")}]


def fit_crop(crop: int, sides: list[int], multiple: int) -> int:
    """``crop``, at most the smallest side, rounded down to a multiple of the model's ``multiple``."""
    crop = min([crop] + sides)
    crop -= crop % multiple
    if crop < multiple:
        raise TrainError(f"frames of {min(sides)} pixels are smaller than the base's minimum side {multiple}")
    return crop


def validation_items(cfg: Config, store: Store, keys: list, spps: list[int]) -> dict | None:
    """The first ``diffusion.val_frames`` val frames (frame i at ``spps[i % len]``) as model inputs, a scorer
    (mean PSNR on x/(1+x) against GT_clean) and the noisy input's and first estimate's scores; None without any."""
    f = cfg.diffusion
    keys = keys[:f.val_frames]
    if not keys:
        return None
    ds = DenoisePairs(store, keys, spps, crop=None, seed=cfg.seed, tonemap=f.tonemap, estimator=estimator_and_id(cfg)[0])
    items = [ds[i] for i in range(len(ds))]
    refs = [from_model(it["target"], f.tonemap).numpy() for it in items]

    def score(images) -> float:
        return float(np.mean([min(psnr(from_model(im, f.tonemap).numpy(), ref), PSNR_CEILING)
                              for im, ref in zip(images, refs)]))

    base = {"noisy_psnr": score([it["noisy"] for it in items]), "estimate_psnr": score([it["image"] for it in items]),
            "frames": len(items), "spp": [spps[i % len(spps)] for i in range(len(items))]}
    return {"items": items, "score": score, "base": base}


# ---- shared by the diffusion runs (this one, the stand-in base's, the OIDN-based one) --------------


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


def plot_history(path, history: list[dict], title: str) -> None:
    """The training loss and, where validated, the val PSNR beside the noisy input's."""
    curves = {"train loss": [(h["epoch"], h["train_loss"]) for h in history
                             if h["train_loss"] is not None and np.isfinite(h["train_loss"])]}
    right = {}
    if any(h.get("val") for h in history):
        right = {"val PSNR (dB)": [(h["epoch"], h["val"]["psnr"]) for h in history if h.get("val")],
                 "noisy input PSNR": [(h["epoch"], h["val"]["noisy_psnr"]) for h in history if h.get("val")]}
    plot_curves(path, curves, title, right=right, right_label="PSNR (dB)")
