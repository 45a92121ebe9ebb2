"""The stand-in base: an IF-II-style super-resolution prior trained on clean images (``make pretrain``).

No foundation-model weights can be fetched here, so the default base is ours: the same UNet
layout as DeepFloyd IF stage II, trained the way IF-II was, as a super-resolution model, on clean
images we have: every GT_clean frame of the store's train split and any folder the user names
(``pretrain.images``: PNG/JPEG in sRGB, or EXRs with R, G, B radiance).

Degradation (the "low-res image" the base is conditioned on), per crop x in model space:

    x_low = up_k(down_k(x)) + σ·n,   k ∈ pretrain.scales,  σ ~ U(0, pretrain.noise),  n ~ N(0, I)

(area down-sampling, bilinear up-sampling). The base then learns p(x | x_low) by the same
ε-MSE + L_t objective as the Control Module (``train.train.fit``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset

from pipeline.exr import StoreError
from pipeline.store import Store

from .data import augment, random_crop, to_model

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".exr"}


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """The sRGB transfer function's inverse (IEC 61966-2-1), for 8-bit pictures as radiance."""
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


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
    return srgb_to_linear(rgb)


def degrade(x: torch.Tensor, scale: int, sigma: float, gen: torch.Generator) -> torch.Tensor:
    """up_k(down_k(x)) + σ·n for a (C, H, W) model-space image; H, W multiples of ``scale``."""
    if scale > 1:
        low = F.avg_pool2d(x[None], scale)
        x = F.interpolate(low, scale_factor=scale, mode="bilinear", align_corners=False)[0]
    return x + sigma * torch.randn(x.shape, generator=gen)


class SuperResolutionPairs(Dataset):
    """Random crops of clean pictures: ``noisy`` = degraded crop, ``target`` = the crop (model space).

    ``crop`` must be a multiple of every scale and no larger than the smallest picture.
    """

    def __init__(self, pictures: list[np.ndarray], crop: int, crops_per_image: int, scales: list[int],
                 noise: float, seed: int = 0, tonemap: str = "log"):
        if not pictures:
            raise StoreError("no pictures to pretrain on: run make dataset first (GT_clean frames) "
                             "or name folders in pretrain.images")
        self.pictures = [np.ascontiguousarray(np.moveaxis(to_model(p, tonemap), 2, 0), np.float32) for p in pictures]
        self.crop, self.per, self.scales, self.noise, self.seed = crop, crops_per_image, scales, noise, seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.pictures) * self.per

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng([self.seed, self.epoch, index])
        pic = self.pictures[index // self.per]
        (x,) = random_crop([pic], self.crop, rng)
        (x,) = augment([x], bool(rng.integers(2)), bool(rng.integers(2)), int(rng.integers(4)))
        scale = int(rng.choice(self.scales))
        x = torch.from_numpy(np.ascontiguousarray(x))
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        return {"noisy": degrade(x, scale, float(rng.uniform(0, self.noise)), gen).float(), "target": x}


def gather_pictures(store_path: str, folders: list[str]) -> tuple[list[np.ndarray], list[str]]:
    """Every GT_clean frame of the store's train split, then every picture in ``folders``."""
    pictures, sources = [], []
    store = Store(store_path)
    if store.manifest_path.exists():
        for key in store.frames("train"):
            if store.image_path(key.scene, key.frame, "gt_clean").exists():
                pictures.append(store.read_image(key.scene, key.frame, "gt_clean", buffers=["color"])[0]["color"])
                sources.append(f"{key.scene}/{key.frame:03d}/gt_clean")
    for folder in folders:
        root = Path(folder)
        if not root.is_dir():
            raise StoreError(f"pretrain.images: {folder}: not a folder")
        for path in sorted(p for p in root.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES):
            pictures.append(load_picture(path))
            sources.append(str(path))
    return pictures, sources
