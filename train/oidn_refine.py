"""The diffusion denoiser on OIDN (``diffusion.base: oidn``): training run, sampler and denoiser.

    make train SPP=any diffusion.base=oidn          → runs/<...>/diffusion_sppany[_<name>]/

The model is ``train.oidn_control.ControlledOIDN`` (OIDN frozen, a Control Module reading every
buffer); the formulation is the refine one (``train.formulation``): the diffused signal is the
residual around OIDN's output in OIDN's output space (PU of the exposed radiance),

    y = (PU(x · s) − x_est) / residual_scale,      x_est = the base's own output,

with x₀-prediction over IF's cosine schedule rescaled to zero terminal SNR, so one DDIM step from
t = T is the network's direct estimate, more steps and several samples are there for the
uncertainty. Training (``RefineTask``, reading top to bottom: model, data, optimiser; the step;
validation) draws t with ``t_focus`` on the sampler's steps, and the loss lives where the metrics
are read, each crop by its gain over OIDN:

    L = w(t) · [ MSE_R(x̂₀, x) / MSE_R(x_est, x) + hdr_weight · L1_PU(x̂₀, x) / L1_PU(x_est, x) ]

(R: the x/(1+x) tonemap PSNR is read on; PU: OIDN's HDR space, where highlights keep their
relative error, as HDR-FLIP sees them; each ratio has a small floor). Crops come from the pack
(``train.oidn_pack``) with OIDN's augmentation and buffer-group dropout. AdamW on the Control
Module only, warm-up and cosine decay, an EMA of its weights (validated and saved), DDP under
torchrun as ``train.train``. The run folder: ``control.safetensors`` (the Control Module, EMA),
``base.tza`` (the frozen base's float16 weights, so the run is self-contained), ``model.json``,
``last.safetensors``, ``train.json``, ``loss.png``.
"""
from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from mcdenoise.pipeline import oidn_net, oidn_weights, tza, weights
from mcdenoise.pipeline.checkpoint import NanGuard, plot_curves
from mcdenoise.pipeline.color import reinhard
from mcdenoise.pipeline.config import Config, ConfigError
from mcdenoise.pipeline.errors import CheckpointError, TrainError
from mcdenoise.pipeline.exr import atomic_write_bytes, atomic_write_json, read_json
from mcdenoise.pipeline.fit import Task, apply_update, fit
from mcdenoise.pipeline.metrics import PSNR_CEILING, psnr
from mcdenoise.pipeline.numerics import repair_nonfinite, shorten_normals
from mcdenoise.pipeline.runs import pick_device, run_dir
from mcdenoise.pipeline.store import Store, sha256

from .formulation import Formulation, snr_weight
from .model import oidn_ft_blob
from .oidn_control import ControlledOIDN
from .oidn_pack import Crops, concat_packs, cond_names, ensure_pack, inputs, load_pack, pack_path, present
from .train import autocast_dtype, dist_info, dist_shutdown, ema_weights, lr_factor, make_ema, run_machine

FORMAT = weights.FORMATS["oidn_control"]
NETWORK = "rt_hdr_alb_nrm"      # the base of models whose model.json predates diffusion.base_network
FLOOR_R, FLOOR_PU = 1e-7, 1e-5  # floors of the per-crop ratios (MSE on the tonemap, L1 in PU)


# ---- the base ----------------------------------------------------------------------------------


def base_blob(cfg: Config) -> tuple[bytes, str]:
    """(the base's float16 TZA blob, what it is): ``diffusion.base`` 'oidn' (OIDN's ``diffusion.base_network``,
    from ``oidn.weights`` or pyoidn), 'oidn_ft' (this config's oidn_ft run of that network, as exported) or a
    .tza file of it."""
    base, network = cfg.diffusion.base, cfg.diffusion.base_network
    if base == "oidn":
        return oidn_weights.load(network, oidn_weights.source(network, cfg.oidn.weights)), f"OIDN {network}"
    if base == "oidn_ft":
        from .oidn_ft import export_blob, load_run
        folder = run_dir(cfg, "oidn_ft", variant=network)
        return export_blob(load_run(folder, cfg)[0]), f"oidn_ft run {folder} (blend {cfg.oidn_ft.blend:g})"
    return oidn_weights.load(network, base), str(base)


def clean_aux(meta: dict) -> bool:
    """Whether a model (its model.json) feeds its base prefiltered albedo and normal."""
    return oidn_weights.clean_aux(meta.get("base_network", NETWORK))


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


def is_oidn_base(cfg: Config) -> bool:
    return cfg.diffusion.on_oidn()


# ---- the loss ----------------------------------------------------------------------------------


def hdr_of(pu: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """HDR radiance of OIDN-space images (B, 3, h, w) at exposures ``scale`` (B,)."""
    return oidn_net.from_pu(pu.clamp(min=0.0)) / scale[:, None, None, None]


def relative_loss(out: torch.Tensor, est: torch.Tensor, target: torch.Tensor, scale: torch.Tensor,
                  hdr_weight: float) -> tuple[torch.Tensor, dict]:
    """Per crop (B,): the tonemapped MSE over OIDN's, plus ``hdr_weight`` × the PU L1 over OIDN's."""
    def mse_r(a):
        return ((reinhard(hdr_of(a, scale)) - reinhard(hdr_of(target, scale))) ** 2).flatten(1).mean(1)

    def l1(a):
        return (a - target).abs().flatten(1).mean(1)

    with torch.no_grad():
        ref_r, ref_pu = mse_r(est) + FLOOR_R, l1(est) + FLOOR_PU
    r, h = mse_r(out) / ref_r, l1(out) / ref_pu
    return r + hdr_weight * h, {"tonemap": r.detach().mean(), "pu": h.detach().mean()}


# ---- sampling ----------------------------------------------------------------------------------


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


# ---- the training run --------------------------------------------------------------------------


class StoreSource:
    """The data of a config's store: the train split as the pack (``train.oidn_pack``), the first
    ``val_frames`` val frames whole, each at the run's smallest, middle and largest sample count."""

    def __init__(self, cfg: Config, network: str | None = None):
        """``network``: the base's (default ``diffusion.base_network``); a ``_calb_cnrm`` one reads prefiltered aux."""
        self.cfg, self.store = cfg, Store(cfg.store)
        self.clean_aux = oidn_weights.clean_aux(network or cfg.diffusion.base_network)
        self.train_keys, self.val_keys = self.store.training_frames()
        self.extra = [(store, store.training_frames()[0]) for store in map(Store, cfg.diffusion.extra_stores)]

    def spps(self, spp) -> list[int]:
        return self.store.spp_choices(spp)

    def train_pack(self, quiet: bool) -> dict[str, torch.Tensor]:
        packs = [load_pack(ensure_pack(self.store, self.train_keys, self.pack_path("train"), quiet, self.clean_aux))]
        for i, (store, keys) in enumerate(self.extra):
            packs.append(load_pack(ensure_pack(store, keys, self.pack_path(f"train_extra{i}"), quiet, self.clean_aux)))
        return concat_packs(packs)

    def pack_path(self, split: str) -> Path:
        return pack_path(self.cfg.runs, split, self.clean_aux)

    def val_items(self, spps: list[int], frames: int) -> list[dict]:
        items = []
        for key in self.val_keys[:frames]:
            ref = self.store.read_image(key.scene, key.frame, "gt_clean", ["color"])[0]["color"]
            for spp in sorted({spps[0], spps[len(spps) // 2], spps[-1]}):
                x, cond, scale = inputs(self.store.read(key.scene, key.frame, spp), spp, clean_aux=self.clean_aux)
                items.append({"x": torch.from_numpy(x)[None], "cond": torch.from_numpy(cond)[None], "scale": scale,
                              "ref": ref, "spp": spp})
        return items


class PackSource:
    """Data carried as packs (the GPU recipe: crops of a store's pack, each crop its own frame): every
    item of ``train`` trains, every item of ``val`` validates against its target."""

    def __init__(self, train: Path, val: Path):
        self.train, self.val = load_pack(train), load_pack(val)

    def spps(self, spp) -> list[int]:
        return sorted({int(s) for s in self.train["spp"]})

    def train_pack(self, quiet: bool) -> dict[str, torch.Tensor]:
        return self.train

    def val_items(self, spps: list[int], frames: int) -> list[dict]:
        v = self.val
        return [{"x": v["x"][i][None].float(), "cond": v["cond"][i][None].float(), "scale": float(v["scale"][i]),
                 "ref": v["target"][int(v["frame"][i])].permute(1, 2, 0).numpy(), "spp": int(v["spp"][i])}
                for i in range(len(v["spp"]))]


class RefineTask(Task):
    """The Control Module on OIDN, trained on the store's train split (see the module docstring)."""

    minimize = False          # validation PSNR
    validate_initial = True   # epoch 0 is OIDN exactly: the run must beat it to keep anything

    def __init__(self, cfg: Config, spp="any", quiet: bool = False, source=None, folder: Path | None = None,
                 init: Path | None = None):
        """``source``: where the data come from (``StoreSource(cfg)``: the config's store; the GPU recipe passes
        carried crop packs); ``folder``: the run folder (default ``<runs>/diffusion_spp<N>[_name]``); ``init``: a
        trained model folder whose base and Control Module the run starts from (else OIDN and a new one)."""
        d = self.d = cfg.diffusion
        self.cfg, self.quiet = cfg, quiet
        init = init or (Path(d.init) if d.init else None)
        # the base's network: a warm start keeps its model's
        self.network = (weights.read_record(init, "oidn_control", "").get("base_network", NETWORK) if init is not None
                        else d.base_network)
        self.source = source or StoreSource(cfg, self.network)
        self.spps = self.source.spps(spp)
        self.rank, self.world = dist_info()
        self.folder = folder or run_dir(cfg, "diffusion", spp)
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
        self.form = dataclasses.replace(form, estimate="oidn", residual=True)
        if self.form.paper or self.form.prediction != "sample":
            raise TrainError("diffusion.base=oidn trains the refine formulation with x0 prediction "
                             "(diffusion.prediction=sample)")
        torch.manual_seed(cfg.seed)
        base = oidn_net.UNet.from_tza(tza.read(self.blob, self.base_what))
        self.model = ControlledOIDN(base, len(cond_names()), control=d.control).to(self.device)
        if self.model.control is None:
            raise TrainError("diffusion.control=false with diffusion.base=oidn is OIDN itself: nothing to train")
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
        w = snr_weight(self.noise_sched, t, "sample", self.form.snr_gamma, self.form.snr_floor).to(self.device)
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
            out = oidn_net.network_output(mean, it["scale"], (H, W))[0].permute(1, 2, 0).cpu().numpy()
            stock = oidn_net.network_output(est, it["scale"], (H, W))[0].permute(1, 2, 0).cpu().numpy()
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
        save(self.folder, self.model, self.blob, self.base_what, self.network, self.form, self.spps,
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
            record["sigma"] = calibrate(load_refiner(self.folder, str(self.device)), self.val, self.cfg.seed)
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


# ---- uncertainty -------------------------------------------------------------------------------

SIGMA_STEPS, SIGMA_SAMPLES = 3, 4     # the sampling the evaluator's uncertainty row uses (ours_s3_k4)


def calibrate(refiner: "OIDNRefiner", items: list[dict], seed: int = 0) -> dict:
    """One scale for the samples' per-pixel standard deviation, fitted on validation images: the
    median of |error| / σ over the pixels with σ > 0, divided by 0.6745 (the median of |N(0, 1)|), so a
    Gaussian error with the scaled σ has half its pixels within 0.6745 σ. Robust to the heavy tails of
    rendering errors, unlike a least-squares fit. Fitted at the refiner's ``strength``, which scales both
    the mean's change and the samples' spread, but not the error by the same factor."""
    ratios = []
    for it in items:
        H, W = it["ref"].shape[:2]
        hdr, s = refiner.refine(torch.as_tensor(it["x"]), torch.as_tensor(it["cond"]), it["scale"], H, W,
                                SIGMA_STEPS, 0, None, seed, SIGMA_SAMPLES, refiner.strength)
        e = np.abs(hdr - it["ref"]).mean(2).ravel()
        s = s.mean(2).ravel()
        ratios.append(e[s > 0] / s[s > 0])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    scale = float(np.median(r) / 0.6745) if r.size else 1.0
    return {"scale": scale, "steps": SIGMA_STEPS, "samples": SIGMA_SAMPLES, "pixels": int(r.size),
            "strength": refiner.strength}


# ---- saving and loading a run ------------------------------------------------------------------


def save(folder: Path, model: ControlledOIDN, blob: bytes, what: str, network: str, form: Formulation,
         spps: list[int], record: dict) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "base.tza").exists() or (folder / "base.tza").read_bytes() != blob:
        atomic_write_bytes(folder / "base.tza", lambda tmp: Path(tmp).write_bytes(blob))
    weights.save(folder, "oidn_control", model.control.state_dict(), {
        "base": "base.tza", "base_network": network, "base_what": what, "base_sha256": hashlib.sha256(blob).hexdigest(),
        "cond_channels": cond_names(), "spp": spps, "formulation": form.record(), **record}, weights="control.safetensors")


def load(folder: str | Path, device="cpu") -> tuple[ControlledOIDN, dict]:
    """(the controlled model in eval mode, model.json) of a run or an exported model folder."""
    folder = Path(folder)
    meta = weights.read_record(folder, "oidn_control", "run `make train SPP=any diffusion.base=oidn`")
    blob = (folder / meta["base"]).read_bytes()
    weights.check_sha256(blob, meta["base_sha256"], f"{folder / meta['base']}: the base", "restore it or retrain")
    if meta["cond_channels"] != cond_names():
        raise CheckpointError(f"{folder / 'model.json'}: trained on another condition layout "
                              f"({len(meta['cond_channels'])} channels, this code makes {len(cond_names())}); retrain")
    model = ControlledOIDN(oidn_net.UNet.from_tza(tza.read(blob, str(folder / meta["base"]))), len(cond_names()))
    model.control.load_state_dict({k: v.float() for k, v in weights.load_tensors(folder / "control.safetensors").items()})
    return model.to(device).eval(), meta


class OIDNRefiner:
    """A trained run as the evaluator and ``denoise`` use it (the interface of ``train.infer.Denoiser``)."""

    clamp_note = "pixels beyond OIDN's output range (65504 after exposure) clamped to its end"   # with last_clamped

    def __init__(self, model: ControlledOIDN, meta: dict, device, base_only: bool = False, folder: Path | None = None):
        self.model, self.meta, self.device, self.folder = model, meta, device, folder
        self.formulation = Formulation.from_record(meta["formulation"])
        self.sigma_scale = float((meta.get("sigma") or {}).get("scale", 1.0))
        self.clean_aux = clean_aux(meta)   # a _calb_cnrm base reads albedo and normal prefiltered by OIDN
        if base_only:
            self.model.control = None
        self.name = "base_only" if base_only else "ours"
        # model.json ``control_without_groups: false``: on colour, albedo and normal alone (none of GROUPS: an
        # EXR from another renderer) the base runs alone, where validation found the Control Module worse
        self.control_without_groups = bool(meta.get("control_without_groups", True))
        # model.json ``strength`` (``export --strength``): how much of the Control Module's change it applies
        self.strength = check_strength(meta.get("strength", 1.0), f"{folder or 'the model'}/model.json: strength")
        self.last_repaired = self.last_clamped = 0
        self.last_black = self.last_estimate_only = self.last_base_only = False
        self.last_shortened = 0        # normals longer than 1 scaled to unit length (garbage layers)
        self.last_seconds = 0.0
        self.fallback = ""

    def denoise(self, buffers: dict[str, np.ndarray], spp: int, skip: int | None = None, seed: int = 0,
                rotation=None, variance=None, steps: int | None = None, start: str | None = None, samples: int = 1,
                with_std: bool = False, strength: float | None = None):
        """HDR (H, W, 3) float32 (and the per-pixel std of ``samples`` samples with ``with_std``);
        ``strength``: the fraction of the Control Module's change applied (default: the model's)."""
        strength = self.strength if strength is None else check_strength(strength, "strength")
        t0 = time.perf_counter()
        buffers = {k: np.array(v, dtype=np.float32, copy=True) for k, v in buffers.items()}
        self.last_repaired = sum(repair_nonfinite(buffers).values())
        self.last_clamped, self.last_base_only = 0, False
        self.last_shortened = shorten_normals(buffers["normal"]) if "normal" in buffers else 0
        color = buffers["color"]
        self.last_black = not np.any(color)
        self.last_estimate_only = not all(a in buffers for a in ("albedo", "normal"))
        if self.last_black:
            hdr = std = np.zeros_like(color)
        elif self.last_estimate_only:   # the base reads albedo and normal: OIDN on what there is
            hdr, std = self._oidn_only(buffers), np.zeros_like(color)
        else:
            self.last_base_only = not self.control_without_groups and not any(present(buffers).values())
            hdr, std = self._sample(buffers, spp, skip, seed, steps, start, samples, strength)
        self.last_seconds = time.perf_counter() - t0
        return (hdr, std) if with_std else hdr

    def _oidn_only(self, buffers: dict[str, np.ndarray]) -> np.ndarray:
        """OIDN on the layers there are: with the model folder's fine-tuned weights for them
        (``oidn_ft/<network>.tza``, OIDN fine-tuned on our data) when it has them, else OIDN's own."""
        from mcdenoise.pipeline import oidn
        network = oidn_weights.network_for("albedo" in buffers, False)
        blob_path = oidn_ft_blob(self.folder, network) if self.folder is not None else None
        self.fallback = str(blob_path) if blob_path is not None and blob_path.exists() else f"OIDN {network}"
        blob = blob_path.read_bytes() if blob_path is not None and blob_path.exists() else None
        return oidn.denoise({k: v for k, v in buffers.items() if k in ("color", "albedo")}, weights=blob)

    def _sample(self, buffers, spp, skip, seed, steps, start, samples, strength=1.0):
        x, cond, scale = inputs(buffers, int(spp), clean_aux=self.clean_aux)
        H, W = buffers["color"].shape[:2]
        control = self.model.control
        if self.last_base_only:
            self.model.control = None
        try:
            hdr, std_hdr = self.refine(torch.from_numpy(x)[None], torch.from_numpy(cond)[None], scale, H, W, steps,
                                       skip, start, seed, samples, strength)
        finally:
            self.model.control = control
        return hdr, std_hdr * self.sigma_scale

    def refine(self, x: torch.Tensor, cond: torch.Tensor, scale: float, H: int, W: int, steps, skip, start, seed,
               samples, strength: float) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) HDR and the samples' unscaled per-pixel std for OIDN-space inputs (``inputs``, batch of
        one): ``sample``, then ``strength`` of the Control Module's change; what ``denoise`` returns and
        ``calibrate`` fits σ on."""
        mean, std, est = sample(self.model, x.to(self.device), cond.to(self.device), self.formulation, steps, skip,
                                start, seed, samples)
        mean, std = with_strength(mean, std, est, strength)
        # OIDN's output space ends at 1 (PU of float16's largest value, 65504 after exposure); a Control
        # Module pushed past it by inputs unlike its training would overflow the inverse
        # transfer to inf: such pixels are clamped to the range's end and counted.
        self.last_clamped = int((mean[..., :H, :W] > 1.0).any(dim=1).sum())
        return self.to_hdr(mean.clamp(max=1.0), std, scale, H, W)

    @staticmethod
    def to_hdr(mean: torch.Tensor, std: torch.Tensor, scale: float, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) HDR of an OIDN-space mean and its std (times the local slope of the inverse transfer)."""
        hdr = oidn_net.network_output(mean, scale, (H, W))
        slope = (oidn_net.network_output(mean + 1e-4, scale, (H, W)) - hdr) / 1e-4
        as_image = lambda t: np.ascontiguousarray(t[0].permute(1, 2, 0).float().cpu().numpy())  # noqa: E731
        return as_image(hdr), as_image(slope.abs() * std[..., :H, :W])


def load_refiner(folder: str | Path, device: str = "auto", base_only: bool = False) -> OIDNRefiner:
    dev = pick_device(device)
    model, meta = load(folder, dev)
    return OIDNRefiner(model, meta, dev, base_only, Path(folder))


def train(cfg: Config, spp="any", quiet: bool = False) -> dict:
    """Train (or resume) the Control Module on OIDN; ``pipeline.fit``'s summary."""
    try:
        return fit(RefineTask(cfg, spp, quiet), quiet=quiet)
    finally:
        dist_shutdown()
