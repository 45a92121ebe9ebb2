"""The stand-in base: a restoration prior of radiance in IF-II's layout (``make pretrain``).

No foundation-model weights can be fetched here, so the default base is ours: the same UNet
layout as DeepFloyd IF stage II, trained on what we have: the GT_clean frames of the store's
train split, their low-spp stacks, and any folder the user names (``pretrain.images``: PNG/JPEG
in sRGB, or EXRs with R, G, B radiance).

Its second input (where IF-II reads the low-resolution image) is a degraded image y of the clean
crop x (model space), drawn per crop:

- with probability ``pretrain.real``, a real low-spp render of the frame at a random sample count
  of the stacks, passed through the formulation's first estimate (OIDN) when it has one, so the
  prior learns exactly the degradation it will refine;
- otherwise a synthetic degradation (``degrade``): area down-sampling by k ∈ ``pretrain.scales``
  and bilinear up-sampling, Gaussian noise of std σ ~ U(0, ``pretrain.noise``), heavy-tailed
  (Student-t, 2 degrees of freedom) noise of the same scale, and fireflies (a fraction
  ``pretrain.fireflies`` of pixels pushed towards white).

The base learns p(x | y) in the configured formulation (``train.formulation``; the paper's
ε-MSE + L_t when it is the paper's): ``PretrainTask`` is the Control Module's run
(``train.train.ControlTask``: the step, the validation, the files) with the base as the trained
module and these pairs as data. With the refine formulation its last convolution starts at zero, so
the untrained base returns y.

    python -m pipeline pretrain        (make pretrain)  -> pretrain(cfg)   runs/<..>/base/ (or pretrain.out)
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset

from mcdenoise.pipeline import weights
from mcdenoise.pipeline.color import srgb_to_linear
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.exr import StoreError
from mcdenoise.pipeline.fit import fit
from mcdenoise.pipeline.runs import pick_device, run_dir
from mcdenoise.pipeline.store import Store

from . import base as base_lib, diffusion
from .control import ControlledDenoiser, zero_module
from .data import augment, random_crop, to_model, to_planar
from .estimate import Estimator
from .formulation import Formulation
from .model import estimator_and_id
from .pack import PackPairs, ensure_pack, pack_path
from .train import ControlTask, autocast_dtype, dist_info, fit_crop, validation_items

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".exr"}


def load_picture(path: Path) -> np.ndarray:
    """(H, W, 3) linear radiance from a PNG/JPEG (sRGB) or an EXR with R, G, B channels."""
    if path.suffix.lower() == ".exr":
        import OpenEXR
        try:
            with OpenEXR.File(str(path), separate_channels=True) as f:
                ch = f.channels()
                if not all(c in ch for c in "RGB"):
                    raise StoreError(f"{path}: EXR without R, G, B channels (has {', '.join(ch)})")
                return np.stack([ch[c].pixels.astype(np.float32) for c in "RGB"], axis=2)
        except StoreError:
            raise
        except Exception as exc:
            raise StoreError(f"{path}: cannot read EXR ({exc})") from None
    from PIL import Image
    try:
        with Image.open(path) as im:
            rgb = np.asarray(im.convert("RGB"), np.float32) / 255.0
    except Exception as exc:
        raise StoreError(f"{path}: cannot read image ({exc})") from None
    return srgb_to_linear(rgb).astype(np.float32)   # 8-bit sRGB pictures as radiance


def degrade(x: torch.Tensor, scale: int, sigma: float, gen: torch.Generator, fireflies: float = 0.0) -> torch.Tensor:
    """A synthetic degradation of a (C, H, W) model-space image (H, W multiples of ``scale``):
    up_k(down_k(x)) + σ·(Gaussian + heavy-tailed) noise + fireflies, clamped to [−1, 1]."""
    if scale > 1:
        low = F.avg_pool2d(x[None], scale)
        x = F.interpolate(low, scale_factor=scale, mode="bilinear", align_corners=False)[0]
    gauss = torch.randn(x.shape, generator=gen)
    # Student-t with 2 dof: N / sqrt(chi2_2 / 2); chi2_2 / 2 is Exp(1) = -log U.
    heavy = torch.randn(x.shape, generator=gen) / (-torch.log(torch.rand(x.shape, generator=gen).clamp_min(1e-12))).sqrt()
    y = x + sigma * (gauss + 0.5 * heavy.clamp(-20, 20))
    if fireflies > 0:
        hot = torch.rand(x.shape[-2:], generator=gen) < fireflies
        y = torch.where(hot[None], torch.ones_like(y), y)
    return y.clamp(-1.0, 1.0)


class RestorationPairs(Dataset):
    """Random crops of clean pictures: ``target`` = the crop, ``noisy``/``image`` = its degradation
    (model space; see the module docstring). ``frames``: per picture, a source of real degraded
    versions (``(store, key)``: read at a random spp of ``spp_choices`` through ``estimator``; or a
    ``PackPairs`` and the pack item indices of the frame) or None; ``estimator``: the first estimate
    (``train.estimate``) applied to real renders. ``crop`` must be a multiple of every scale and no
    larger than the smallest picture."""

    def __init__(self, pictures: list[np.ndarray], crop: int, crops_per_image: int, scales: list[int],
                 noise: float, seed: int = 0, tonemap: str = "log", frames: list | None = None,
                 real: float = 0.0, spp_choices: list[int] | None = None, estimator: Estimator | None = None,
                 fireflies: float = 0.002):
        if not pictures:
            raise StoreError("no pictures to pretrain on: run make dataset first (GT_clean frames) "
                             "or name folders in pretrain.images")
        self.pictures = [np.ascontiguousarray(np.moveaxis(to_model(p, tonemap), 2, 0), np.float32) for p in pictures]
        self.crop, self.per, self.scales, self.noise, self.seed = crop, crops_per_image, scales, noise, seed
        self.frames = frames or [None] * len(pictures)
        self.real, self.spp_choices, self.estimator = real, spp_choices or [4], estimator or Estimator()
        self.tonemap, self.fireflies = tonemap, fireflies
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.pictures) * self.per

    def _real(self, i: int, rng: np.random.Generator) -> np.ndarray:
        source, where = self.frames[i]
        if not isinstance(source, Store):   # a pack: one of the frame's items, decoded already
            return source.t["image"][int(rng.choice(where))].float().numpy()
        buffers = source.read(where.scene, where.frame, int(rng.choice(self.spp_choices)), rng=rng)
        est = self.estimator(buffers)[0]
        return to_planar(buffers["color"] if est is None else est, self.tonemap)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng([self.seed, self.epoch, index])
        i = index // self.per
        real = self.frames[i] is not None and rng.random() < self.real
        arrays = [self.pictures[i]] + ([self._real(i, rng)] if real else [])
        arrays = random_crop(arrays, self.crop, rng)
        arrays = augment(arrays, bool(rng.integers(2)), bool(rng.integers(2)), int(rng.integers(4)))
        x = torch.from_numpy(np.ascontiguousarray(arrays[0]))
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        scale, sigma = int(rng.choice(self.scales)), float(rng.uniform(0, self.noise))
        y = torch.from_numpy(np.ascontiguousarray(arrays[1])) if real else degrade(x, scale, sigma, gen, self.fireflies)
        return {"noisy": y.float(), "image": y.float(), "target": x}


def gather_pictures(store_path: str, folders: list[str]) -> tuple[list[np.ndarray], list[str], list]:
    """Every GT_clean frame of the store's train split, then every picture in ``folders``; the third
    list holds (store, key) for store frames (their real renders) and None for pictures."""
    pictures, sources, frames = [], [], []
    store = Store(store_path)
    if store.manifest_path.exists():
        for key in store.frames_with("train"):
            pictures.append(store.read_image(key.scene, key.frame, "gt_clean", buffers=["color"])[0]["color"])
            sources.append(f"{key.scene}/{key.frame:03d}/gt_clean")
            frames.append((store, key))
    for folder in folders:
        root = Path(folder)
        if not root.is_dir():
            raise StoreError(f"pretrain.images: {folder}: not a folder")
        for path in sorted(p for p in root.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES):
            pictures.append(load_picture(path))
            sources.append(str(path))
            frames.append(None)
    return pictures, sources, frames


# ---- the training run ----------------------------------------------------------------------------


def pretrain(cfg: Config, quiet: bool = False) -> dict | None:
    """Train (or resume) a new stand-in base into ``<runs>/base`` (``pretrain.out``); with ``pretrain.epochs``
    0 write the initialised one. The summary of ``pipeline.fit`` (None without training)."""
    task = PretrainTask(cfg, quiet)
    if cfg.pretrain.epochs == 0:   # with the refine formulation the initialised base returns its image input exactly
        task.save_best({"epoch": 0, "val": None, "train_loss": None})
        if not quiet:
            print(f"untrained base written to {task.out}", flush=True)
        return None
    summary = fit(task, quiet=quiet)
    if not quiet:
        print(f"base written to {task.out} ({sum(x.numel() for x in task.unet.parameters()) / 1e6:.2f} M parameters); "
              f"use it with diffusion.base={task.out}", flush=True)
    return summary


class PretrainTask(ControlTask):
    """A new IF-II-layout base trained alone on ``RestorationPairs`` (no Control Module); written to ``out``."""

    fmt = weights.FORMATS["base"]
    # Not epoch 0: a zero last layer is the identity, and a frozen identity base would give the Control
    # Module no gradient (its residuals only reach the output through the base's last layer).
    validate_initial = False

    def __init__(self, cfg: Config, quiet: bool = False):
        p = self.s = cfg.pretrain
        d = cfg.diffusion
        self.cfg, self.quiet, self.rank, self.world = cfg, quiet, *dist_info()
        self.out = run_dir(cfg, "base")
        self.folder = self.out.parent / (self.out.name + ".train")
        self.name, self.epochs, self.time_budget_s, self.nan_limit = "pretrain", p.epochs, p.time_budget_s, p.nan_limit
        self.warmup_steps, self.grad_clip, self.epoch_steps = p.warmup_steps, p.grad_clip, 0
        self.title = "stand-in base: restoration prior"
        self.device = pick_device(p.device)
        self.autocast = autocast_dtype(p.precision, self.device)
        form = self.form = Formulation.from_config(d)

        # The model: a new base (zero last layer for the refine formulation), no Control Module.
        pictures, sources, frames = gather_pictures(cfg.store, list(p.images))
        config = base_lib.default_config(list(p.channels), p.layers_per_block)
        self.unet, self.prompt = base_lib.build(config, seed=cfg.seed)
        if not form.paper:
            zero_module(self.unet.conv_out)   # the untrained base returns its image input (see train.formulation)
        self.model = ControlledDenoiser(self.unet, self.prompt, None, train_base=True).to(self.device)
        self.state, self.params = self.unet, list(self.unet.parameters())

        # The data: restoration pairs of the store's GT_clean frames and the pictures; val frames as the Control Module's.
        lcm = math.lcm(self.model.multiple, *[int(s) for s in p.scales])
        crop = fit_crop(p.crop, [min(x.shape[:2]) for x in pictures] if pictures else [p.crop], lcm)
        store = Store(cfg.store)
        spps = store.spp_choices("any") if store.manifest_path.exists() and store.scenes() else [4]
        if d.pack and any(frames):
            frames = pack_sources(cfg, store, frames, quiet)
        self.data = RestorationPairs(pictures, crop, p.crops_per_image, [int(s) for s in p.scales], p.noise, cfg.seed,
                                     d.tonemap, frames=frames, real=p.real, spp_choices=spps,
                                     estimator=estimator_and_id(cfg)[0], fireflies=p.fireflies)
        val_keys = store.frames_with("val") if store.manifest_path.exists() and p.epochs > 0 else []
        self.val = validation_items(cfg, store, val_keys, spps) if val_keys and not form.paper else None

        # The optimiser (no EMA) and the settings a resume must share.
        self.objective = diffusion.objective(self.device) if form.paper else form.objective(list(d.train_steps))
        self.optimizers = torch.optim.AdamW(self.params, lr=p.lr, weight_decay=p.weight_decay)
        self.ema = None
        self.fingerprint = {"config": config, "seed": cfg.seed, "crop": crop, "pictures": len(pictures),
                            "formulation": form.record(),
                            **{k: getattr(p, k) for k in ("epochs", "batch_size", "crops_per_image", "lr",
                                                           "weight_decay", "scales", "noise", "fireflies", "real")}}
        self.card = {"what": "stand-in IF-II-layout base trained by make pretrain (restoration prior of radiance)",
                     "pictures": len(pictures), "sources": sources[:50], "tonemap": d.tonemap,
                     "formulation": form.record()}

    def save_best(self, entry: dict) -> None:
        base_lib.save(self.out, self.unet, self.prompt,
                      self.card | {"epoch": entry["epoch"], "metrics": entry["val"], "train_loss": entry["train_loss"]})


def pack_sources(cfg: Config, store: Store, frames: list, quiet: bool) -> list:
    """Real degraded versions of the store's frames from the train pack: (pack, item indices) per frame."""
    keys = store.frames_with("train")
    est, est_id = estimator_and_id(cfg)
    path = ensure_pack(store, keys, pack_path(cfg.runs, "train", est.kind), cfg.diffusion.tonemap, est, quiet, est_id)
    pack = PackPairs(path, crop=None, tonemap=cfg.diffusion.tonemap, estimate=est.kind)
    items: dict[int, list[int]] = {}
    for i, f in enumerate(pack.t["frame"].tolist()):
        items.setdefault(f, []).append(i)
    where = {str(k): items[j] for j, k in enumerate(keys)}
    return [None if src is None else (pack, where[str(src[1])]) for src in frames]
