"""Apply the trained cleaner: GT_clean = C_θ(F, GT1) (paper eq. 3) for every frame of the store.

Each frame gets ``gt_clean.exr`` next to its ``gt1.exr``: the buffer ``color`` (float32 HDR) with
``color.variance`` = 0 (the cleaned image is the training target and is treated as exact; the EXR
writer stores the constant 0 as a header constant, so it costs no space). The header record
(``mcdenoise``) names the image, its source (``gt1``) and ``cleaner_sha256``, the SHA-256 of the
``model.safetensors`` that made it. ``STORE/cleaner.json`` (written atomically, only when it
changes) records the checkpoint, its hash, epoch and validation metrics, and per frame the hash
that made its gt_clean.

Idempotent: a frame whose gt_clean.exr already records the current checkpoint's hash is skipped,
so a rerun does nothing; a new checkpoint (new hash) rewrites every frame. Frames that are not
complete yet (no frame.json / gt1) are skipped and counted.

``denoise`` is also the inference entry point of the Isik baseline for the evaluator:

    model, meta = clean.model.load_model("runs/default/isik_spp4")
    inputs, radiance = clean.data.frame_inputs(store.read(scene, frame, spp=4))
    hdr = clean.apply.denoise(model, inputs, radiance)          # (H, W, 3) float32
"""
from __future__ import annotations

import time

import numpy as np
import torch

from mcdenoise.pipeline.config import Config, pick_device, run_dir
from mcdenoise.pipeline.exr import StoreError, atomic_write_json, read_json
from mcdenoise.pipeline.progress import progress
from mcdenoise.pipeline.store import Store, sha256

from .data import RADIANCE, frame_inputs
from .model import AffinityDenoiser, load_model

MANIFEST = "cleaner.json"
# Context around a tile: the three dilated 7×7 kernels alone reach 3·(1+2+4) = 21 pixels (24 with
# the range term's 3×3 patches), the U-Net further; 32 pixels make tile seams invisible in practice.
TILE_MARGIN = 32


@torch.no_grad()
def denoise(model: AffinityDenoiser, inputs: np.ndarray, radiance: np.ndarray, tile: int = 512,
            device: str | torch.device = "cpu") -> np.ndarray:
    """Run the model on one frame: inputs (C, H, W), radiance (3, H, W) → HDR (H, W, 3) float32.

    Frames larger than ``tile`` are processed in tiles with ``TILE_MARGIN`` pixels of context, so
    memory stays bounded whatever the frame size.
    """
    model.eval()
    device = torch.device(device)
    H, W = radiance.shape[-2:]
    out = np.empty((3, H, W), np.float32)
    step = max(1, int(tile))
    for y0 in range(0, H, step):
        for x0 in range(0, W, step):
            y1, x1 = min(H, y0 + step), min(W, x0 + step)
            m = 0 if (H <= step and W <= step) else TILE_MARGIN
            ya, yb, xa, xb = max(0, y0 - m), min(H, y1 + m), max(0, x0 - m), min(W, x1 + m)
            x = torch.from_numpy(np.ascontiguousarray(inputs[:, ya:yb, xa:xb]))[None].to(device)
            r = torch.from_numpy(np.ascontiguousarray(radiance[:, ya:yb, xa:xb]))[None].to(device)
            y = model(x, r)[0].float().cpu().numpy()
            out[:, y0:y1, x0:x1] = y[:, y0 - ya:y1 - ya, x0 - xa:x1 - xa]
    return np.ascontiguousarray(np.moveaxis(out, 0, 2))


def apply_cleaner(cfg: Config, quiet: bool = False) -> dict:
    """Write gt_clean.exr for every complete frame; returns counts (written, skipped, incomplete)."""
    t0 = time.perf_counter()
    store = Store(cfg.store)
    ckpt = run_dir(cfg, "cleaner") / "model.safetensors"
    if not ckpt.exists():
        raise StoreError(f"{ckpt}: no cleaner checkpoint; train it first (make gt-clean)")
    digest = sha256(ckpt)
    device = pick_device(cfg.clean.device)
    model, meta = load_model(ckpt, device)
    manifest_path = store.root / MANIFEST
    old = read_json(manifest_path, "cleaner manifest") if manifest_path.exists() else {}
    frames_done = dict(old.get("frames", {})) if old.get("sha256") == digest else {}
    stats = {"written": 0, "skipped": 0, "incomplete": 0}
    keys = store.frames()
    bar = progress(keys, desc="gt-clean", unit="frame", disable=quiet, leave=False)
    for key in bar:
        if not store.is_frame_complete(key.scene, key.frame, ["gt1"]):
            stats["incomplete"] += 1
            continue
        # A kill during a previous run's write leaves its temporary file; only this stage
        # writes gt_clean, so any such file is stale.
        for tmp in store.frame_dir(key.scene, key.frame).glob(".gt_clean.exr.*.tmp"):
            tmp.unlink(missing_ok=True)
        if _current(store, key, digest):
            stats["skipped"] += 1
            frames_done[str(key)] = digest
            continue
        buffers = store.read_image(key.scene, key.frame, "gt1")[0]
        inputs, radiance = frame_inputs(buffers)
        hdr = denoise(model, inputs, radiance, tile=cfg.clean.tile, device=device)
        store.write_image(key.scene, key.frame, "gt_clean",
                          {RADIANCE: hdr, f"{RADIANCE}.variance": np.zeros_like(hdr)},
                          meta={"image": "gt_clean", "scene": key.scene, "frame": key.frame, "source": "gt1",
                                "cleaner_sha256": digest, "cleaner_epoch": meta.get("epoch")},
                          camera=_camera(store, key))
        frames_done[str(key)] = digest
        stats["written"] += 1
    record = {"checkpoint": str(ckpt), "sha256": digest, "epoch": meta.get("epoch"), "metrics": meta.get("metrics"),
              "smape_eps": meta.get("smape_eps"), "frames": dict(sorted(frames_done.items()))}
    if record != old:
        atomic_write_json(manifest_path, record)
    stats["seconds"] = time.perf_counter() - t0
    stats["sha256"] = digest
    if not quiet:
        print(f"gt-clean: {stats['written']} frames written, {stats['skipped']} up to date, "
              f"{stats['incomplete']} incomplete (not rendered yet) in {stats['seconds']:.1f} s; "
              f"cleaner {digest[:12]} (epoch {meta.get('epoch')}) -> {store.root}/scenes/*/*/gt_clean.exr",
              flush=True)
    return stats


def _camera(store: Store, key):
    """The frame's camera for gt_clean's header, as its other images carry it; None for a frame rendered
    before cameras were recorded (its images have none either)."""
    try:
        return store.camera(key.scene, key.frame)
    except StoreError:
        return None


def _current(store: Store, key, digest: str) -> bool:
    """gt_clean.exr exists, is readable and was made by the checkpoint with this hash."""
    if not store.image_path(key.scene, key.frame, "gt_clean").exists():
        return False
    try:
        return store.image_header(key.scene, key.frame, "gt_clean").get("cleaner_sha256") == digest
    except StoreError:
        return False        # a damaged file is rewritten
