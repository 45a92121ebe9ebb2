"""What the diffusion denoiser sees: model-space radiance, the auxiliary condition, augmentation, pairs.

**Radiance** (noisy input and target) lives in [−1, 1] (``to_model`` / ``from_model``, exact
inverses on [0, 6]): clamp to [0, 6], range-compress with ``pipeline.color.log_compress``
(A·log(1 + x), A = 0.51; paper eq. 5) or, with ``tonemap: gamma``, ``gamma_compress``
(A·x^γ, A = 0.47, γ = 1/2.4; eq. 4), then ``2y − 1``. Both compressions map 6 to ~0.99.

**Condition** F (``condition``, channels listed by ``aux_names``): ``pipeline.features``' table,
every buffer of the schema, with this model's choices (``encoding``):

- the noisy radiance buffers (``color`` and its five components): as the radiance above;
- ``normal``: in **camera space** (x right, y up, z towards the camera), mapped to [0, 1] by
  (n + 1)/2. Camera space makes flips and rotations of the image act on normals consistently
  (``augment``) and makes the condition independent of where the scene sits in the world. The
  camera comes from ``frame.json``'s ``camera_to_world`` (or the scene's camera description);
  without either, world-space normals are used as they are;
- ``depth``, the other features and the per-buffer relative variances: as the table says (the
  same encoding the cleaner uses);
- the sample count: a constant map log2(spp)/6 (1 at 64 spp), so one model can serve any spp.

A buffer the store left out (a feature a scene does not need) is its documented background
value, 0, so the channel count never depends on the scene.
"""
from __future__ import annotations

import functools

import numpy as np
import torch
from torch.utils.data import Dataset

from mcdenoise.pipeline import color, features
from mcdenoise.pipeline.store import FrameKey, Store

from .estimate import Estimator, extra_names

CLAMP = 6.0


# ---- radiance ↔ model space ------------------------------------------------------------------


def to_model(x, tonemap: str = "log"):
    """HDR radiance → [−1, 1] (clamped to [0, 6] first)."""
    x = color.clamp(x, 0.0, CLAMP)
    y = color.log_compress(x) if tonemap == "log" else color.gamma_compress(x)
    return 2.0 * y - 1.0


def from_model(y, tonemap: str = "log"):
    """[−1, 1] → HDR radiance in [0, 6]; the exact inverse of ``to_model`` on [0, 6]."""
    y = (color.clamp(y, -1.0, 1.0) + 1.0) / 2.0
    x = color.inverse_log_compress(y) if tonemap == "log" else color.inverse_gamma_compress(y)
    return color.clamp(x, 0.0, CLAMP)


# ---- the condition ---------------------------------------------------------------------------


def encoding(tonemap: str = "log") -> features.Encoding:
    """This model's choices of the feature table: radiance in model space, normals in [0, 1], the spp channel."""
    return features.Encoding(radiance=functools.partial(to_model, tonemap=tonemap), normals01=True, spp=True)


def aux_names(estimate: str = "none") -> list[str]:
    """One name per condition channel, in order; a first estimate of several components adds them
    (``train.estimate.extra_names``)."""
    return features.names(encoding()) + extra_names(estimate)


AUX_CHANNELS = len(aux_names())


def camera_rotation(record: dict | None, scene_manifest: dict | None, frame: int) -> np.ndarray | None:
    """3×3 world→camera rotation (rows: right, up, towards-camera) of a frame, or None if unknown."""
    m = (record or {}).get("camera_to_world")
    if m is not None:
        m = np.asarray(m, np.float64)[:3, :3]
        left, up, fwd = m[:, 0], m[:, 1], m[:, 2]
    else:
        try:
            pose = scene_manifest["description"]["camera"]["frames"][frame]
        except (KeyError, IndexError, TypeError):
            return None
        o, t, u = (np.asarray(pose[k], np.float64) for k in ("origin", "target", "up"))
        fwd = (t - o) / np.linalg.norm(t - o)
        left = np.cross(u, fwd)
        left /= np.linalg.norm(left)
        up = np.cross(fwd, left)
    # Mitsuba's camera frame is (left, up, forward); image x grows to the right, z towards us.
    return np.stack([-left, up, -fwd]).astype(np.float32)


def condition(buffers: dict[str, np.ndarray], spp: int, rotation: np.ndarray | None = None,
              tonemap: str = "log") -> np.ndarray:
    """The condition F (AUX_CHANNELS, H, W) float32 from one image's buffers (H, W, C arrays)."""
    return features.encode(buffers, encoding(tonemap), spp, rotation)


def model_inputs(buffers: dict[str, np.ndarray], spp: int, rotation: np.ndarray | None = None,
                 tonemap: str = "log", estimates: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(noisy radiance (3, H, W) in [−1, 1], condition (C, H, W)) of one image; ``estimates``: the first
    estimate's components (HDR), appended to the condition when there are several (``aux_names``)."""
    aux = condition(buffers, spp, rotation, tonemap)
    if estimates and len(estimates) > 1:
        aux = np.concatenate([aux] + [to_planar(e, tonemap) for e in estimates], axis=0)
    return to_planar(buffers["color"], tonemap), aux


def to_planar(hdr: np.ndarray, tonemap: str = "log") -> np.ndarray:
    """(H, W, 3) HDR → (3, H, W) float32 in model space."""
    return np.ascontiguousarray(np.moveaxis(to_model(hdr.astype(np.float32), tonemap), 2, 0), np.float32)


# ---- augmentation ----------------------------------------------------------------------------

_N0 = aux_names().index("normal.X")
_NORMAL = slice(_N0, _N0 + 3)


def augment(arrays: list[np.ndarray], flip_x: bool, flip_y: bool, rot: int, aux_index: int | None = None) -> list[np.ndarray]:
    """Flip and rotate (C, H, W) arrays alike; in ``arrays[aux_index]`` turn the camera-space normals too.

    Normals are stored in [0, 1] as (n + 1)/2. A horizontal flip mirrors x (n_x → −n_x), a
    vertical flip mirrors y, a quarter turn counter-clockwise (``np.rot90``) maps (x, y) → (−y, x).
    """
    out = []
    for i, a in enumerate(arrays):
        a = a.copy()
        is_aux = i == aux_index
        n = a[_NORMAL] * 2.0 - 1.0 if is_aux else None
        if flip_x:
            a = a[..., :, ::-1]
            if is_aux:
                n = n[..., :, ::-1] * np.array([-1, 1, 1], np.float32)[:, None, None]
        if flip_y:
            a = a[..., ::-1, :]
            if is_aux:
                n = n[..., ::-1, :] * np.array([1, -1, 1], np.float32)[:, None, None]
        for _ in range(rot % 4):
            a = np.rot90(a, 1, axes=(-2, -1))
            if is_aux:
                n = np.rot90(n, 1, axes=(-2, -1))
                n = np.stack([-n[1], n[0], n[2]])
        a = np.ascontiguousarray(a)
        if is_aux:
            a[_NORMAL] = (n + 1.0) / 2.0
        out.append(a)
    return out


def random_crop(arrays: list[np.ndarray], crop: int, rng: np.random.Generator) -> list[np.ndarray]:
    H, W = arrays[0].shape[-2:]
    crop = min(crop, H, W)
    y, x = int(rng.integers(0, H - crop + 1)), int(rng.integers(0, W - crop + 1))
    return [a[..., y:y + crop, x:x + crop] for a in arrays]


# ---- training pairs --------------------------------------------------------------------------


def frame_rotation(store: Store, key: FrameKey) -> np.ndarray | None:
    return camera_rotation(store.frame_record(key.scene, key.frame), store.scene_manifest(key.scene), key.frame)


class DenoisePairs(Dataset):
    """Low-spp buffers of a frame (random stacks in training, the first ones in validation) → gt_clean.

    Items: ``noisy`` (3, h, w), ``aux`` (AUX_CHANNELS, h, w), ``target`` (3, h, w), all float32
    in model space, and ``image`` (3, h, w), the first estimate (``estimator``, run on the whole
    frame before cropping) or, without one, the noisy radiance again. ``spp_choices`` with several
    values draws the sample count per item (the ``SPP=any`` model); in validation (``crop=None``)
    item i uses ``spp_choices[i % len]``, so every sample count is validated. Randomness from
    ``default_rng([seed, epoch, index])``: reproducible epochs, exact resume.
    """

    def __init__(self, store: Store, keys: list[FrameKey], spp_choices: list[int], crop: int | None,
                 crops_per_frame: int = 1, seed: int = 0, tonemap: str = "log", augment: bool = True,
                 estimator: Estimator | None = None):
        if not keys:
            raise ValueError("no frames")
        self.store, self.keys, self.spp_choices = store, list(keys), [int(s) for s in spp_choices]
        self.crop, self.seed, self.tonemap, self.do_augment = crop, int(seed), tonemap, augment
        self.estimator = estimator or Estimator()
        self.crops_per_frame = int(crops_per_frame) if crop else 1
        self.epoch = 0
        self._rot: dict = {}
        self._target_cache: dict = {}

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.keys) * self.crops_per_frame

    def _target(self, key: FrameKey) -> np.ndarray:
        if key not in self._target_cache:
            gt = self.store.read_image(key.scene, key.frame, "gt_clean", buffers=["color"])[0]["color"]
            self._target_cache[key] = to_planar(gt, self.tonemap)
        return self._target_cache[key]

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        key = self.keys[index // self.crops_per_frame]
        train = self.crop is not None
        rng = np.random.default_rng([self.seed, self.epoch, index])
        spp = int(rng.choice(self.spp_choices)) if train else self.spp_choices[index % len(self.spp_choices)]
        buffers = self.store.read(key.scene, key.frame, spp, rng=rng if train else None)
        if key not in self._rot:
            self._rot[key] = frame_rotation(self.store, key)
        est, parts = self.estimator(buffers)
        noisy, aux = model_inputs(buffers, spp, self._rot[key], self.tonemap, parts)
        image = noisy if est is None else to_planar(est, self.tonemap)
        arrays = [noisy, aux, self._target(key), image]
        if train:
            arrays = random_crop(arrays, self.crop, rng)
            if self.do_augment:
                arrays = augment(arrays, bool(rng.integers(2)), bool(rng.integers(2)), int(rng.integers(4)),
                                 aux_index=1)
        return {k: torch.from_numpy(np.ascontiguousarray(a))
                for k, a in zip(("noisy", "aux", "target", "image"), arrays)}
