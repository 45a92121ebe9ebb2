"""Command-line entry points of the diffusion stage, called by ``python -m pipeline``.

    train --model diffusion --spp 4|16|64|any   → cmd_train(cfg, spp)      runs/<..>/diffusion_spp4/
    pretrain                                    → cmd_pretrain(cfg)        runs/<..>/base/ (or pretrain.out)
    denoise (--frame SCENE/FRAME | --exr FILE)  → cmd_denoise(...)         an EXR with the denoised colour
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from pipeline.config import Config
from pipeline.exr import write_image
from pipeline.metrics import psnr
from pipeline.store import FrameKey, Store

from . import base as base_lib
from .data import DenoisePairs, from_model, frame_rotation
from .model import FORMAT, base_folder, build, run_dir, save
from .pretrain import SuperResolutionPairs, gather_pictures
from .sampler import sample
from .train import Job, TrainError, autocast_dtype, dist_shutdown, fit, pick_device


def _frames(store: Store, split: str) -> list[FrameKey]:
    if split not in store.manifest().get("splits", {}):
        return []
    return [k for k in store.frames(split) if store.image_path(k.scene, k.frame, "gt_clean").exists()]


def _fit_crop(crop: int, sides: list[int], multiple: int) -> int:
    crop = min([crop] + sides)
    crop -= crop % multiple
    if crop < multiple:
        raise TrainError(f"frames of {min(sides)} pixels are smaller than the base's minimum side {multiple}")
    return crop


def _validator(store: Store, keys: list[FrameKey], spp: int, cfg: Config, device, autocast):
    """Val PSNR (x/(1+x)) of the sampler at ``val_skip`` on the first ``val_frames`` val frames."""
    keys = keys[:cfg.diffusion.val_frames]
    if not keys:
        return None
    ds = DenoisePairs(store, keys, [spp], crop=None, seed=cfg.seed, tonemap=cfg.diffusion.tonemap)
    items = [ds[i] for i in range(len(ds))]
    tm = cfg.diffusion.tonemap

    def validate(model) -> dict:
        model.eval()
        rows = []
        for it in items:
            noisy, aux = it["noisy"][None].to(device), it["aux"][None].to(device)
            out = sample(model, noisy, aux, skip=cfg.diffusion.val_skip, seed=cfg.seed,
                         threshold_ratio=cfg.diffusion.threshold_ratio, autocast_dtype=autocast,
                         variance=cfg.diffusion.variance)
            ref = from_model(it["target"], tm).numpy()
            rows.append((psnr(from_model(out[0].float().cpu(), tm).numpy(), ref),
                         psnr(from_model(it["noisy"], tm).numpy(), ref)))
        model.train()
        return {"psnr": float(np.mean([min(r[0], 999.0) for r in rows])),
                "noisy_psnr": float(np.mean([min(r[1], 999.0) for r in rows])), "frames": len(rows),
                "skip": cfg.diffusion.val_skip}
    return validate


def cmd_train(cfg: Config, spp, quiet: bool = False) -> int:
    """Train the Control Module for ``spp`` (or 'any') from the store's low-spp stacks to GT_clean."""
    f = cfg.diffusion
    store = Store(cfg.store)
    if not store.manifest_path.exists():
        raise TrainError(f"{store.root}: no dataset; run `make dataset` first")
    choices = store.spp_choices(spp)
    train_keys, val_keys = _frames(store, "train"), _frames(store, "val")
    if not train_keys:
        raise TrainError(f"{store.root}: no training frame with gt_clean; run `make gt-clean`")
    if not f.control and not f.train_base:
        raise TrainError("diffusion.control=false with train_base=false leaves nothing to train; the base-only "
                         "ablation needs no training (the evaluator runs it from the base)")
    device = pick_device(f.device)
    model = build(cfg).to(device)
    sides = [min(store.scene_manifest(s)["resolution"]) for s in {k.scene for k in train_keys}]
    crop = _fit_crop(f.crop, sides, model.multiple)
    ds = DenoisePairs(store, train_keys, choices, crop, f.crops_per_frame, cfg.seed, f.tonemap)
    autocast = autocast_dtype(f.precision, device)
    folder = run_dir(cfg, spp)
    fp = {"spp": str(spp), "seed": cfg.seed, "base_sha256": _base_hash(cfg), "crop": crop,
          **{k: getattr(f, k) for k in ("tonemap", "batch_size", "crops_per_frame", "lr", "weight_decay",
                                         "warmup_steps", "grad_clip", "train_base", "control", "epochs")}}

    def save_best(record):
        save(folder, model, cfg, str(spp), record)

    trainable = torch.nn.ModuleDict({k: m for k, m in (("control", model.control),
                                                        ("base", model.base if f.train_base else None)) if m})
    job = Job(name=folder.name, folder=folder, model=model, trainable=trainable, params=model.trainable_parameters(),
              train_ds=ds, validate=_validator(store, val_keys, choices[-1] if str(spp) != "any" else 4, cfg, device,
                                               autocast),
              save_best=save_best, epochs=f.epochs, batch_size=f.batch_size, lr=f.lr, weight_decay=f.weight_decay,
              warmup_steps=f.warmup_steps, grad_clip=f.grad_clip, nan_limit=f.nan_limit,
              time_budget_s=f.time_budget_s, seed=cfg.seed, fingerprint=fp, device=device, autocast=autocast,
              fmt=FORMAT, title=f"Control Module, {spp} spp -> GT_clean")
    try:
        fit(job, quiet=quiet)
    finally:
        dist_shutdown()
    return 0


def _base_hash(cfg: Config) -> str:
    from pipeline.store import sha256
    path = base_folder(cfg) / base_lib.WEIGHTS
    if not path.exists():
        raise TrainError(f"{path}: base weights missing; run `make pretrain` or set diffusion.base")
    return sha256(path)


def cmd_pretrain(cfg: Config, quiet: bool = False) -> int:
    """Train a new stand-in base (IF-II layout) as a super-resolution prior on clean pictures."""
    p = cfg.pretrain
    out = Path(p.out) if p.out else Path(cfg.runs) / "base"
    pictures, sources = gather_pictures(cfg.store, list(p.images))
    device = pick_device(cfg.diffusion.device)
    config = base_lib.default_config(list(p.channels), p.layers_per_block)
    from .control import ControlledDenoiser
    unet, prompt = base_lib.build(config, seed=cfg.seed)
    model = ControlledDenoiser(unet, prompt, None, train_base=True).to(device)
    lcm = math.lcm(model.multiple, *[int(s) for s in p.scales])
    crop = _fit_crop(p.crop, [min(x.shape[:2]) for x in pictures] if pictures else [p.crop], lcm)
    ds = SuperResolutionPairs(pictures, crop, p.crops_per_image, [int(s) for s in p.scales], p.noise, cfg.seed,
                              cfg.diffusion.tonemap)
    folder = out.parent / (out.name + ".train")
    fp = {"config": config, "seed": cfg.seed, "crop": crop, "pictures": len(pictures),
          **{k: getattr(p, k) for k in ("epochs", "batch_size", "crops_per_image", "lr", "weight_decay", "scales",
                                         "noise")}}
    card = {"what": "stand-in IF-II-layout base trained by make pretrain (super-resolution prior)",
            "pictures": len(pictures), "sources": sources[:50], "tonemap": cfg.diffusion.tonemap}

    def save_best(record):
        base_lib.save(out, unet, prompt, card | record)

    job = Job(name="pretrain", folder=folder, model=model, trainable=unet, params=list(unet.parameters()),
              train_ds=ds, validate=None, save_best=save_best, epochs=p.epochs, batch_size=p.batch_size, lr=p.lr,
              weight_decay=p.weight_decay, warmup_steps=cfg.diffusion.warmup_steps, grad_clip=cfg.diffusion.grad_clip,
              nan_limit=cfg.diffusion.nan_limit, time_budget_s=p.time_budget_s, seed=cfg.seed, fingerprint=fp,
              device=device, autocast=autocast_dtype(cfg.diffusion.precision, device), fmt="mcdenoise-base",
              title="stand-in base: super-resolution prior")
    fit(job, quiet=quiet)
    if not quiet:
        print(f"base written to {out} ({sum(x.numel() for x in unet.parameters()) / 1e6:.2f} M parameters); "
              f"use it with diffusion.base={out}", flush=True)
    return 0


def cmd_denoise(cfg: Config, spp: int, frame: str | None, exr: str | None, out: str, skip: int | None,
                seed: int | None, base_only: bool = False, quiet: bool = False) -> int:
    """Denoise one frame of the store (``SCENE/FRAME``) or one EXR and write ``out`` (EXR, ``color``)."""
    from .infer import load_denoiser

    if (frame is None) == (exr is None):
        raise TrainError("give exactly one of --frame SCENE/FRAME or --exr FILE")
    f = cfg.diffusion
    den = load_denoiser(run_dir(cfg, spp), f.device, base_only, f.tile, f.tile_overlap, f.precision)
    rotation = None
    if frame is not None:
        store = Store(cfg.store)
        try:
            scene, idx = frame.split("/")
            key = FrameKey(scene, int(idx))
        except ValueError:
            raise TrainError(f"--frame {frame!r}: expected SCENE/FRAME, e.g. s00000/000") from None
        buffers = store.read(key.scene, key.frame, int(spp))
        rotation = frame_rotation(store, key)
        source = f"{store.root}/{frame}"
    else:
        from pipeline.exr import read_layers
        buffers = read_layers(Path(exr))
        source = exr
    hdr = den.denoise(buffers, int(spp), skip=skip, seed=cfg.seed if seed is None else seed, rotation=rotation,
                      variance=f.variance)
    meta = {"image": "denoised", "source": source, "spp": int(spp), "method": den.name, "variance": f.variance,
            "skip": den.meta.get("skip") if skip is None else skip, "repaired_nonfinite": den.last_repaired,
            "seconds": round(den.last_seconds, 3)}
    write_image(Path(out), {"color": hdr, "color.variance": np.zeros_like(hdr)}, meta=meta)
    if not quiet:
        print(f"denoised {source} ({hdr.shape[1]}x{hdr.shape[0]}, {spp} spp, {den.name}) in {den.last_seconds:.1f} s"
              f" -> {out}" + (f"; {den.last_repaired} non-finite input values replaced by 0" if den.last_repaired
                              else ""), flush=True)
    return 0

