"""Command-line entry points of the diffusion stage, called by ``python -m pipeline``.

    train --model diffusion --spp 4|16|64|any   → cmd_train(cfg, spp)      runs/<..>/diffusion_spp4/
    pretrain                                    → cmd_pretrain(cfg)        runs/<..>/base/ (or pretrain.out)
    denoise (--frame SCENE/FRAME | --exr FILE)  → cmd_denoise(...)         an EXR with the denoised colour
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import torch

from mcdenoise.pipeline.config import PAPER_STEPS, Config
from mcdenoise.pipeline.exr import StoreError, write_image
from mcdenoise.pipeline.metrics import PSNR_CEILING, psnr
from mcdenoise.pipeline.runs import pick_device, run_dir as runs_dir
from mcdenoise.pipeline.store import FrameKey, Store, sha256

from . import base as base_lib
from .data import DenoisePairs, frame_rotation, from_model
from .formulation import Formulation
from .model import FORMAT, base_folder, build, estimator, find_run, isik_folder, new_base, run_dir, save
from .pack import PackPairs, ensure_pack, pack_path
from .pretrain import RestorationPairs, gather_pictures
from .sampler import sample
from .train import Job, TrainError, autocast_dtype, dist_shutdown, fit


def _fit_crop(crop: int, sides: list[int], multiple: int) -> int:
    crop = min([crop] + sides)
    crop -= crop % multiple
    if crop < multiple:
        raise TrainError(f"frames of {min(sides)} pixels are smaller than the base's minimum side {multiple}")
    return crop


def _validator(store: Store, keys: list[FrameKey], spps: list[int], cfg: Config, device, autocast):
    """Val PSNR (x/(1+x)) of the configured sampler on the first ``val_frames`` val frames (frame i at
    ``spps[i % len]``), beside the noisy input's and the first estimate's."""
    keys = keys[:cfg.diffusion.val_frames]
    if not keys:
        return None
    f = cfg.diffusion
    form = Formulation.from_config(f)
    ds = DenoisePairs(store, keys, spps, crop=None, seed=cfg.seed, tonemap=f.tonemap, estimator=_estimator(cfg)[0])
    items = [ds[i] for i in range(len(ds))]
    refs = [from_model(it["target"], f.tonemap).numpy() for it in items]

    def score(images) -> float:
        return float(np.mean([min(psnr(from_model(im, f.tonemap).numpy(), ref), PSNR_CEILING)
                              for im, ref in zip(images, refs)]))

    base = {"noisy_psnr": score([it["noisy"] for it in items]), "estimate_psnr": score([it["image"] for it in items]),
            "frames": len(items), "spp": [spps[i % len(spps)] for i in range(len(items))]}

    def validate(model) -> dict:
        model.eval()
        outs = []
        for it in items:
            noisy, aux, image = (it[k][None].to(device) for k in ("noisy", "aux", "image"))
            out = sample(model, noisy, aux, image=image, formulation=form,
                         skip=f.val_skip if form.paper else f.skip, seed=cfg.seed,
                         threshold_ratio=f.threshold_ratio, autocast_dtype=autocast, variance=f.variance)
            outs.append(out[0].float().cpu())
        model.train()
        return {"psnr": score(outs), **base, "skip": f.val_skip if form.paper else f.skip,
                "steps": PAPER_STEPS if form.paper else f.steps}
    return validate


def cmd_train(cfg: Config, spp, quiet: bool = False) -> int:
    """Train the Control Module for ``spp`` (or 'any') from the store's low-spp stacks to GT_clean."""
    from . import oidn_refine
    if oidn_refine.is_oidn_base(cfg):
        oidn_refine.train(cfg, spp, quiet=quiet)
        return 0
    f = cfg.diffusion
    store = Store(cfg.store)
    if not store.manifest_path.exists():
        raise TrainError(f"{store.root}: no dataset; run `make dataset` first")
    choices = store.spp_choices(spp)
    train_keys, val_keys = store.frames_with("train"), store.frames_with("val")
    if not train_keys:
        raise TrainError(f"{store.root}: no training frame with gt_clean; run `make gt-clean`")
    if not f.control and not f.train_base:
        raise TrainError("diffusion.control=false with train_base=false leaves nothing to train; the base-only "
                         "ablation needs no training (the evaluator runs it from the base)")
    device = pick_device(f.device)
    folder = run_dir(cfg, spp)
    new_base(cfg, folder)
    model = build(cfg, run=folder).to(device)
    sides = [min(store.scene_manifest(s)["resolution"]) for s in {k.scene for k in train_keys}]
    crop = _fit_crop(f.crop, sides, model.multiple)
    form = Formulation.from_config(f)
    if f.pack:
        est, est_id = _estimator(cfg)
        path = ensure_pack(store, train_keys, pack_path(cfg.runs, "train", form.estimate), f.tonemap, est, quiet,
                           est_id)
        ds = PackPairs(path, crop, f.crops_per_frame, cfg.seed, choices, f.tonemap, form.estimate)
        choices = sorted(set(ds.t["spp"].tolist()) & set(choices))
    else:
        ds = DenoisePairs(store, train_keys, choices, crop, f.crops_per_frame, cfg.seed, f.tonemap,
                          estimator=_estimator(cfg)[0])
    autocast = autocast_dtype(f.precision, device)
    fp = {"spp": str(spp), "seed": cfg.seed, "base_sha256": _base_hash(cfg, folder), "crop": crop,
          "formulation": form.record(), "train_steps": list(f.train_steps), "ema": f.ema,
          **{k: getattr(f, k) for k in ("tonemap", "batch_size", "crops_per_frame", "lr", "weight_decay",
                                         "warmup_steps", "grad_clip", "train_base", "control", "epochs")},
          # only when set, so runs from before the key resume as they were
          **({"epoch_steps": f.epoch_steps} if f.epoch_steps else {})}

    def save_best(record):
        save(folder, model, cfg, str(spp), record)

    trainable = torch.nn.ModuleDict({k: m for k, m in (("control", model.control),
                                                        ("base", model.base if f.train_base else None)) if m})
    job = Job(name=folder.name, folder=folder, model=model, trainable=trainable, params=model.trainable_parameters(),
              train_ds=ds, validate=_validator(store, val_keys, choices, cfg, device, autocast),
              objective=None if form.paper else form.objective(list(f.train_steps)),
              validate_initial=not form.paper, ema=f.ema, epoch_steps=f.epoch_steps, save_best=save_best,
              epochs=f.epochs,
              batch_size=f.batch_size, lr=f.lr, weight_decay=f.weight_decay,
              warmup_steps=f.warmup_steps, grad_clip=f.grad_clip, nan_limit=f.nan_limit,
              time_budget_s=f.time_budget_s, seed=cfg.seed, fingerprint=fp, device=device, autocast=autocast,
              fmt=FORMAT, title=f"Control Module, {spp} spp -> GT_clean")
    try:
        fit(job, quiet=quiet)
    finally:
        dist_shutdown()
    return 0


def _base_hash(cfg: Config, run: Path) -> str:
    from mcdenoise.pipeline.store import sha256
    path = base_folder(cfg, run) / base_lib.WEIGHTS
    if not path.exists():
        raise TrainError(f"{path}: base weights missing; run `make pretrain` or set diffusion.base")
    return sha256(path)


def cmd_pretrain(cfg: Config, quiet: bool = False) -> int:
    """Train a new stand-in base (IF-II layout) as a restoration prior (``train.pretrain``)."""
    p = cfg.pretrain
    out = runs_dir(cfg, "base")
    pictures, sources, frames = gather_pictures(cfg.store, list(p.images))
    device = pick_device(cfg.diffusion.device)
    form = Formulation.from_config(cfg.diffusion)
    config = base_lib.default_config(list(p.channels), p.layers_per_block)
    from .control import ControlledDenoiser, zero_module
    unet, prompt = base_lib.build(config, seed=cfg.seed)
    if not form.paper:
        zero_module(unet.conv_out)   # the untrained base returns its image input (see train.formulation)
    model = ControlledDenoiser(unet, prompt, None, train_base=True).to(device)
    lcm = math.lcm(model.multiple, *[int(s) for s in p.scales])
    crop = _fit_crop(p.crop, [min(x.shape[:2]) for x in pictures] if pictures else [p.crop], lcm)
    store = Store(cfg.store)
    spps = store.spp_choices("any") if store.manifest_path.exists() and store.scenes() else [4]
    if cfg.diffusion.pack and any(frames):
        frames = _pack_sources(cfg, store, frames, quiet)
    ds = RestorationPairs(pictures, crop, p.crops_per_image, [int(s) for s in p.scales], p.noise, cfg.seed,
                          cfg.diffusion.tonemap, frames=frames, real=p.real, spp_choices=spps,
                          estimator=_estimator(cfg)[0], fireflies=p.fireflies)
    folder = out.parent / (out.name + ".train")
    fp = {"config": config, "seed": cfg.seed, "crop": crop, "pictures": len(pictures), "formulation": form.record(),
          **{k: getattr(p, k) for k in ("epochs", "batch_size", "crops_per_image", "lr", "weight_decay", "scales",
                                         "noise", "fireflies", "real")}}
    card = {"what": "stand-in IF-II-layout base trained by make pretrain (restoration prior of radiance)",
            "pictures": len(pictures), "sources": sources[:50], "tonemap": cfg.diffusion.tonemap,
            "formulation": form.record()}

    def save_best(record):
        base_lib.save(out, unet, prompt, card | record)

    if p.epochs == 0:   # the initialised base: with the refine formulation it returns its image input exactly
        save_best({"epoch": 0, "metrics": None, "train_loss": None})
        if not quiet:
            print(f"untrained base written to {out}", flush=True)
        return 0

    val_keys = store.frames_with("val") if store.manifest_path.exists() else []
    validate = _validator(store, val_keys, spps, cfg, device, autocast_dtype(cfg.diffusion.precision, device)) \
        if val_keys and not form.paper else None
    job = Job(name="pretrain", folder=folder, model=model, trainable=unet, params=list(unet.parameters()),
              # Not epoch 0: a zero last layer is the identity, and a frozen identity base would give the Control
              # Module no gradient (its residuals only reach the output through the base's last layer).
              train_ds=ds, validate=validate, validate_initial=False, save_best=save_best, epochs=p.epochs,
              batch_size=p.batch_size, lr=p.lr,
              weight_decay=p.weight_decay, warmup_steps=cfg.diffusion.warmup_steps, grad_clip=cfg.diffusion.grad_clip,
              nan_limit=cfg.diffusion.nan_limit, time_budget_s=p.time_budget_s, seed=cfg.seed, fingerprint=fp,
              device=device, autocast=autocast_dtype(cfg.diffusion.precision, device), fmt="mcdenoise-base",
              title="stand-in base: restoration prior",
              objective=None if form.paper else form.objective(list(cfg.diffusion.train_steps)))
    fit(job, quiet=quiet)
    if not quiet:
        print(f"base written to {out} ({sum(x.numel() for x in unet.parameters()) / 1e6:.2f} M parameters); "
              f"use it with diffusion.base={out}", flush=True)
    return 0


DEFAULT_EXR_SPP = 16


def _exr_spp(path: Path) -> tuple[int, str]:
    """The sample count an EXR's mcdenoise header records, else ``DEFAULT_EXR_SPP`` (the middle of 4..64)."""
    from mcdenoise.pipeline.exr import read_header
    try:
        spp = read_header(path).get("spp")
    except StoreError:
        spp = None
    if isinstance(spp, int) and spp > 0:
        return spp, "from its header"
    return DEFAULT_EXR_SPP, "not recorded in the file: assumed"


def _estimator(cfg: Config):
    """(the configured first estimate, an id of its weights for the pack header)."""
    est = estimator(cfg)
    ident = sha256(isik_folder(cfg) / "model.safetensors") if est.isik is not None else ""
    return est, ident


def _pack_sources(cfg: Config, store: Store, frames: list, quiet: bool) -> list:
    """Real degraded versions of the store's frames from the train pack: (pack, item indices) per frame."""
    keys = store.frames_with("train")
    est, est_id = _estimator(cfg)
    path = ensure_pack(store, keys, pack_path(cfg.runs, "train", est.kind), cfg.diffusion.tonemap, est, quiet, est_id)
    pack = PackPairs(path, crop=None, tonemap=cfg.diffusion.tonemap, estimate=est.kind)
    items: dict[int, list[int]] = {}
    for i, f in enumerate(pack.t["frame"].tolist()):
        items.setdefault(f, []).append(i)
    where = {str(k): items[j] for j, k in enumerate(keys)}
    return [None if src is None else (pack, where[str(src[1])]) for src in frames]


def _warn_if_correlated(exr: str, color: np.ndarray) -> None:
    """A warning on stderr when the input's noise is spatially correlated (pipeline/noise.py)."""
    from mcdenoise.pipeline.noise import CORRELATED_BELOW, correlated_noise

    ratio = correlated_noise(color)
    if ratio is not None:
        print(f"warning: {exr}: its noise looks spatially correlated (neighbour ratio {ratio:.2f} < "
              f"{CORRELATED_BELOW}), as a wide reconstruction filter makes it (Mitsuba's default 'gaussian', "
              "'tent'); OIDN, this denoiser's first estimate, leaves such noise in place. Render with "
              "<rfilter type=\"box\"/> in the film (a nearly noise-free image can read this way too).",
              file=sys.stderr, flush=True)


def cmd_denoise(cfg: Config, spp: int, frame: str | None, exr: str | None, out: str, skip: int | None,
                seed: int | None, base_only: bool = False, quiet: bool = False, steps: int | None = None,
                samples: int | None = None) -> int:
    """Denoise one frame of the store (``SCENE/FRAME``) or one EXR and write ``out`` (EXR: ``color``, the
    mean of ``samples`` samples, and ``std``, their per-pixel standard deviation)."""
    from .infer import load_denoiser

    if (frame is None) == (exr is None):
        raise TrainError("give exactly one of --frame SCENE/FRAME or --exr FILE")
    if frame is not None and spp is None:
        raise TrainError("--frame needs --spp (which of the store's sample counts to denoise)")
    if exr is not None and spp is None:
        spp, how = _exr_spp(Path(exr))
        if not quiet:
            print(f"{exr}: {spp} spp ({how}; pass --spp to say otherwise)", flush=True)
    f = cfg.diffusion
    den = load_denoiser(find_run(cfg, spp), f.device, base_only, f.tile, f.tile_overlap, f.precision)
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
        from mcdenoise.pipeline.exr import read_layers
        buffers = read_layers(Path(exr))
        source = exr
        _warn_if_correlated(exr, buffers["color"])
    samples = f.samples if samples is None else int(samples)
    if samples < 1:
        raise TrainError(f"--samples {samples}: expected at least 1")
    hdr, std = den.denoise(buffers, int(spp), skip=skip, seed=cfg.seed if seed is None else seed, rotation=rotation,
                           variance=f.variance, steps=steps, samples=samples, with_std=True)
    meta = {"image": "denoised", "source": source, "spp": int(spp), "method": den.name, "variance": f.variance,
            "skip": den.meta.get("skip") if skip is None else skip, "steps": steps, "samples": samples,
            "formulation": den.formulation.record(), "repaired_nonfinite": den.last_repaired,
            "clamped_pixels": den.last_clamped, "black_input": den.last_black,
            "estimate_only": den.last_estimate_only, "fallback": getattr(den, "fallback", ""),
            "seconds": round(den.last_seconds, 3)}
    write_image(Path(out), {"color": hdr, "color.variance": np.zeros_like(hdr)}, meta=meta, layers={"std": std})
    if not quiet:
        fallback = getattr(den, "fallback", "")
        alone = (f"; no albedo/normal layers: {fallback} on the colour{' and albedo' if 'albedo' in buffers else ''}"
                 if fallback else "; no variance/albedo/normal layers: the first estimate (OIDN) alone")
        print(f"denoised {source} ({hdr.shape[1]}x{hdr.shape[0]}, {spp} spp, {den.name}) in {den.last_seconds:.1f} s"
              f" -> {out}" + (f"; {den.last_repaired} non-finite input values replaced by 0" if den.last_repaired
                              else "") + (alone if den.last_estimate_only else ""), flush=True)
    return 0



def oidn_weights_for(cfg: Config, network: str) -> tuple[bytes, str]:
    """(the TZA blob, where it came from) that ``denoise --method oidn_ft`` runs for ``network``: the
    config's oidn_ft run of that network."""
    from mcdenoise.pipeline.runs import run_dir as model_dir

    from .oidn_ft import export_blob, load_run
    folder = model_dir(cfg, "oidn_ft", variant=network)
    if (folder / "model.safetensors").exists():
        return export_blob(load_run(folder, cfg)[0]), str(folder)
    raise TrainError(f"no oidn_ft run for OIDN's {network} network in {folder}: train it with "
                     f"`make train MODEL=oidn_ft SPP=any oidn_ft.network={network}`, or give --oidn-weights FILE.tza")


def cmd_denoise_oidn(cfg: Config, frame: str | None, exr: str | None, out: str, method: str,
                     weights_file: str | None, spp: int | None = None, quiet: bool = False) -> int:
    """Denoise a store frame or an EXR with OIDN itself: its built-in network (``oidn``), an oidn_ft
    run (``oidn_ft``) or the weights of ``weights_file``, on the layers the input has (colour; +albedo;
    +albedo+normal), at OIDN's speed."""
    import time

    from mcdenoise.pipeline import oidn, oidn_weights as ow, tza
    from mcdenoise.pipeline.oidn_net import UNet

    if (frame is None) == (exr is None):
        raise TrainError("give exactly one of --frame SCENE/FRAME or --exr FILE")
    buffers, source = _read_input(cfg, frame, exr, spp)
    layers = [a for a in ("albedo", "normal") if a in buffers]
    layers = layers if layers and layers[0] == "albedo" else []
    network = ow.network_for("albedo" in layers, "normal" in layers)
    blob, origin = None, f"pyoidn built-in {network}"
    if weights_file:
        blob, origin = ow.load(network, weights_file), weights_file
        need = (UNet.from_tza(tza.read(blob, weights_file)).in_channels - 3) // 3
        if need > len(layers):
            raise TrainError(f"{weights_file}: these OIDN weights read {3 + 3 * need} channels (colour"
                             f"{', albedo' if need else ''}{', normal' if need > 1 else ''}), but {source} has only "
                             f"{', '.join(['colour', *layers])}")
        layers = layers[:need]
    elif method == "oidn_ft":
        blob, origin = oidn_weights_for(cfg, network)
    t = time.perf_counter()
    hdr = oidn.denoise({"color": buffers["color"], **{a: buffers[a] for a in layers}}, aux=bool(layers), weights=blob)
    seconds = time.perf_counter() - t
    meta = {"image": "denoised", "source": source, "method": method, "weights": origin,
            "inputs": ["color", *layers], "seconds": round(seconds, 3)}
    write_image(Path(out), {"color": hdr, "color.variance": np.zeros_like(hdr)}, meta=meta)
    if not quiet:
        print(f"denoised {source} ({hdr.shape[1]}x{hdr.shape[0]}; {', '.join(['colour', *layers])}) with OIDN "
              f"({origin}) in {seconds:.2f} s -> {out}", flush=True)
    return 0


def _read_input(cfg: Config, frame: str | None, exr: str | None, spp: int | None) -> tuple[dict, str]:
    """The buffers of ``--frame SCENE/FRAME`` (at ``spp``) or ``--exr FILE``, and how to name the source."""
    if exr is not None:
        from mcdenoise.pipeline.exr import read_layers
        buffers = read_layers(Path(exr))
        _warn_if_correlated(exr, buffers["color"])
        return buffers, exr
    if spp is None:
        raise TrainError("--frame needs --spp (which of the store's sample counts to denoise)")
    store = Store(cfg.store)
    try:
        scene, idx = frame.split("/")
        key = FrameKey(scene, int(idx))
    except ValueError:
        raise TrainError(f"--frame {frame!r}: expected SCENE/FRAME, e.g. s00000/000") from None
    return store.read(key.scene, key.frame, int(spp)), f"{store.root}/{frame}"


def cmd_pack(cfg: Config, splits: list[str], quiet: bool = False) -> int:
    """Write the training packs of ``splits`` (``train.pack``) for the configured first estimate."""
    store = Store(cfg.store)
    if not store.manifest_path.exists():
        raise TrainError(f"{store.root}: no dataset; run `make dataset` first")
    est, est_id = _estimator(cfg)
    for split in splits:
        keys = store.frames_with(split)
        if not keys:
            raise TrainError(f"{store.root}: no {split} frame with gt_clean; run `make gt-clean`")
        path = ensure_pack(store, keys, pack_path(cfg.runs, split, est.kind), cfg.diffusion.tonemap, est, quiet, est_id)
        print(f"pack {split}: {len(keys)} frames -> {path} ({path.stat().st_size / 2**20:.1f} MiB)", flush=True)
    return 0
