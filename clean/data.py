"""Network inputs from store buffers, and the training pairs of the cleaner and the Isik baseline.

Input channels: ``pipeline.schema``' table with its default encoding (``ENCODING``): the
radiance buffers as ``log1p(max(x, 0))``, normals as stored (world space: image flips permute
pixels but do not change world-space directions, so augmentation never touches the normal
values), depth relative to the frame's largest, the other features as stored, one
relative-variance channel per buffer; no spp channel. Crops use the whole frame's depth maximum.

The radiance the kernels filter is the HDR ``color`` itself (``radiance``), not an input channel.

Pairs (dicts of float32 tensors ``inputs`` (C, h, w), ``radiance`` (3, h, w), ``target`` (3, h, w)):

- ``CleanerPairs``: GT1 and GT2 of a frame, swapped at random (paper eq. 1): inputs and
  radiance of one, target the other one's ``color``.
- ``BaselinePairs``: the low-spp buffers at ``spp`` (``Store.read``, random stacks in training,
  the first stacks in validation) → target ``gt_clean`` (or another image, e.g. ``gt1``); with a
  list of sample counts (``SPP=any``) each training item draws one.

Training items are random crops with random horizontal/vertical flips; validation items are
whole frames in a fixed order. Randomness comes from ``numpy.random.default_rng([seed, epoch,
index])``: an epoch's items are reproducible, which makes resuming a training run exact.
"""
from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.schema import (
    RELATIVE_VARIANCE_MIN,
    VARIANCE_FLOOR,
    relative_variance_feature as relative_variance_feature,  # re-exported
)
from mcdenoise.pipeline.store import FrameKey, Store, stack_name

RADIANCE = "color"
# Preprocessed frames are kept in memory up to this many bytes (the EXR reads dominate otherwise).
CACHE_BYTES = 1 << 30

ENCODING = schema.Encoding()   # log1p radiance, normals as stored, no spp channel
# The encoded inputs lie in roughly [-20, 20]; every network on them (clean.model's, and any other
# that reads this encoding) clamps them to +-INPUT_CLAMP first, which only guards against
# pathological finite inputs (1e30 would otherwise overflow the convolutions to inf).
INPUT_CLAMP = 1e3
# (key, channels, kind) of every input channel group, in order.
CHANNELS: tuple[tuple[str, int, str], ...] = schema.TABLE
IN_CHANNELS: int = sum(n for _, n, _ in CHANNELS)
# Index of the filtered radiance's relative-variance feature among the input channels: the
# affinity network's range term decodes the pixel variance from it (``decode_variance``).
COLOR_VARIANCE_CHANNEL: int = IN_CHANNELS - len(schema.BUFFERS) + [b.name for b in schema.BUFFERS].index(RADIANCE)


def channel_names() -> list[str]:
    """One name per input channel, e.g. ``color.R``, ``normal.X``, ``depth.variance`` (for JSON sidecars)."""
    return schema.names(ENCODING)


def decode_variance(feature: torch.Tensor, radiance: torch.Tensor) -> torch.Tensor:
    """Inverse of ``relative_variance_feature``: the channel-mean variance (B, 1, H, W) of
    ``radiance`` (B, 3, H, W) from its feature (B, 1, H, W).

    Exact for relative variances above ``RELATIVE_VARIANCE_MIN`` (below it the log's floor makes
    the result at most that floor too large: a conservative error, the filter then averages
    less). The feature is clamped to [0, 2] first (relative variance <= 1e6), so any finite input
    decodes to a finite variance.
    """
    rel = (10.0 ** (6.0 * (feature.clamp(0.0, 2.0) - 1.0)) - RELATIVE_VARIANCE_MIN).clamp(min=0.0)
    mean_square = (radiance.clamp(-1e15, 1e15) ** 2).mean(1, keepdim=True)
    return rel * (mean_square + VARIANCE_FLOOR)


def frame_inputs(buffers: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(inputs (C, H, W), radiance (3, H, W)) float32 from one image's buffers (HxWxC arrays).

    A buffer missing from ``buffers`` (e.g. a feature a reader did not ask for) counts as 0.
    """
    radiance = np.ascontiguousarray(np.moveaxis(buffers[RADIANCE].astype(np.float32), 2, 0))
    return schema.encode(buffers, ENCODING), radiance


def crop_and_flip(arrays: list[np.ndarray], crop: int, rng: np.random.Generator) -> list[np.ndarray]:
    """The same random crop×crop window and flips of several (C, H, W) arrays.

    Flips only permute pixels: our normals are world-space, so their values stay as they are.
    """
    H, W = arrays[0].shape[-2:]
    y = int(rng.integers(0, H - crop + 1))
    x = int(rng.integers(0, W - crop + 1))
    flip_x, flip_y = bool(rng.integers(2)), bool(rng.integers(2))
    out = []
    for a in arrays:
        a = a[..., y:y + crop, x:x + crop]
        if flip_x:
            a = a[..., :, ::-1]
        if flip_y:
            a = a[..., ::-1, :]
        out.append(np.ascontiguousarray(a))
    return out


class _Cache:
    """Keeps computed values until CACHE_BYTES are used, then stops adding (no eviction churn)."""

    def __init__(self, limit: int = CACHE_BYTES):
        self.limit, self.used, self.data = limit, 0, {}

    def get(self, key, make):
        if key in self.data:
            return self.data[key]
        value = make()
        size = sum(a.nbytes for a in value)
        if self.used + size <= self.limit:
            self.data[key] = value
            self.used += size
        return value


class _Pairs(Dataset):
    def __init__(self, store: Store, keys: list[FrameKey], crop: int | None, crops_per_frame: int = 1,
                 seed: int = 0):
        if not keys:
            raise ValueError("no frames to train or validate on")
        self.store, self.keys, self.seed, self.epoch = store, list(keys), int(seed), 0
        self.train = crop is not None
        self.crops_per_frame = int(crops_per_frame) if self.train else 1
        self.crop = None
        if self.train:
            # One crop size for the whole batch: no larger than the smallest frame.
            sides = [min(store.scene_manifest(s)["resolution"]) for s in {k.scene for k in keys}]
            self.crop = max(1, min([int(crop)] + sides))
        self.cache = _Cache()

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.keys) * self.crops_per_frame

    def _rng(self, index: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.epoch, index])

    def _image(self, key: FrameKey, image: str) -> tuple[np.ndarray, np.ndarray]:
        return self.cache.get((key.scene, key.frame, image),
                              lambda: frame_inputs(self.store.read_image(key.scene, key.frame, image)[0]))

    def _target(self, key: FrameKey, image: str) -> np.ndarray:
        def make():
            color = self.store.read_image(key.scene, key.frame, image, buffers=[RADIANCE])[0][RADIANCE]
            return (np.ascontiguousarray(np.moveaxis(color, 2, 0)),)
        return self.cache.get((key.scene, key.frame, image, "target"), make)[0]

    def _item(self, inputs, radiance, target, rng) -> dict[str, torch.Tensor]:
        if self.train:
            inputs, radiance, target = crop_and_flip([inputs, radiance, target], self.crop, rng)
        return {"inputs": torch.from_numpy(inputs), "radiance": torch.from_numpy(radiance),
                "target": torch.from_numpy(target)}


class CleanerPairs(_Pairs):
    """GT1 ↔ GT2 of each frame (swapped at random in training; GT1 → GT2 in validation)."""

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = self._rng(index)
        key = self.keys[index // self.crops_per_frame]
        a, b = ("gt1", "gt2") if not self.train or rng.integers(2) == 0 else ("gt2", "gt1")
        inputs, radiance = self._image(key, a)
        target = self._image(key, b)[1]
        return self._item(inputs, radiance, target, rng)


class BaselinePairs(_Pairs):
    """Low-spp buffers at ``spp`` (random stacks in training, the first ones in validation) → ``target``
    (gt_clean, or another reference such as gt1).

    ``spp`` may be a list (one model for several sample counts): training draws one per item,
    validation has every frame at every count."""

    def __init__(self, store: Store, keys: list[FrameKey], spp: int | list[int], crop: int | None,
                 crops_per_frame: int = 1, seed: int = 0, target: str = "gt_clean"):
        super().__init__(store, keys, crop, crops_per_frame, seed)
        self.spps = [int(s) for s in spp] if isinstance(spp, (list, tuple)) else [int(spp)]
        self.target = target

    def __len__(self) -> int:
        return super().__len__() * (1 if self.train else len(self.spps))

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = self._rng(index)
        if self.train:
            key = self.keys[index // self.crops_per_frame]
            spp = self.spps[int(rng.integers(len(self.spps)))] if len(self.spps) > 1 else self.spps[0]
            inputs, radiance = frame_inputs(self.store.read(key.scene, key.frame, spp, rng=rng))
        else:
            key, spp = self.keys[index // len(self.spps)], self.spps[index % len(self.spps)]
            inputs, radiance = self.cache.get((key.scene, key.frame, f"spp{spp}"),
                                              lambda: frame_inputs(self.store.read(key.scene, key.frame, spp)))
        target = self._target(key, self.target)
        return self._item(inputs, radiance, target, rng)


def usable_frames(store: Store, split: str, images: list[str]) -> list[FrameKey]:
    """Frames of ``split`` that are complete and have every image of ``images`` on disk (none for a split
    the store does not have)."""
    return [k for k in store.frames_with(split, images) if store.is_frame_complete(k.scene, k.frame, ["gt1"])]


def baseline_images(store: Store, key: FrameKey, spp: int, target: str = "gt_clean") -> list[str]:
    """Images the baseline needs for ``key`` at ``spp``: the stacks it averages and its target."""
    sm = store.scene_manifest(key.scene)
    return [stack_name(k) for k in range(max(1, spp // int(sm["stack_spp"])))] + [target]
