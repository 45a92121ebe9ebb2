"""A compact training pack: what the diffusion model reads, decoded once, in one safetensors file per split.

Reading a training pair from the store decodes up to 16 ZIP-compressed EXRs of ~50 channels and
runs the first estimate (OIDN) on it; a pack does that once (``python -m pipeline pack``, ``make
pack``). Per frame and per sample count s of ``PACK_VARIANTS`` it keeps ``variants[s]`` disjoint
stack subsets (variant v averages stacks v·k … v·k + k − 1, k = s / stack_spp, exactly as
``Store.read`` with those stacks), each as model-space arrays:

    noisy (N, 3, H, W) f16   the noisy radiance            (train.data.model_inputs)
    aux   (N, C, H, W) f16   the condition F               (train.data.condition)
    image (N, 3, H, W) f16   the first estimate            (train.estimate; = noisy for "none")
    target (F, 3, H, W) f16  GT_clean, one per frame       frame (N,) i32, spp (N,) i32: which frame, which spp

Float16 on model-space values in [−1, 1] (and condition features mostly in [0, 1]) is within
about 5e-4 of the float32 the store reader gives: below the noise of a 64 spp input and of
GT_clean (tests/test_pack.py checks the round trip). The header (safetensors metadata) records
the frames, the condition's channel names, the tonemap and the estimate, and ``PackPairs``
refuses a pack made with another layout. Only random crops and flips remain to do per item, so a
training step costs the model's time, not the decoder's; the file is loaded
once into memory (float16).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from mcdenoise.pipeline.checkpoint import save_safetensors
from mcdenoise.pipeline.exr import StoreError
from mcdenoise.pipeline.progress import progress
from mcdenoise.pipeline.store import FrameKey, Store, combine_stacks, poolable, stack_name

from .data import augment, aux_names, frame_rotation, model_inputs, random_crop, to_planar
from .estimate import Estimator

FORMAT = "mcdenoise-pack"
PACK_VARIANTS = {4: 2, 16: 1, 64: 1}


def variant_stacks(spp: int, stack_spp: int, variant: int, stacks: int) -> list[int]:
    """The disjoint stack indices of ``variant`` at ``spp`` (ValueError if the store has too few)."""
    k = spp // stack_spp
    if spp % stack_spp or (variant + 1) * k > stacks:
        raise ValueError(f"spp {spp} variant {variant} needs stacks {variant * k}..{(variant + 1) * k - 1}, "
                         f"the store has {stacks} of {stack_spp} spp")
    return list(range(variant * k, (variant + 1) * k))


def fit_variants(variants: dict[int, int], stack_spp: int, stacks: int) -> dict[int, int]:
    """``variants`` limited to what a store with ``stacks`` stacks of ``stack_spp`` can pool disjointly."""
    out = {}
    for spp, count in variants.items():
        if poolable(spp, stack_spp, stacks):
            n = min(int(count), stacks // (spp // stack_spp))
            if n > 0:
                out[int(spp)] = n
    return out


def frame_items(store: Store, key: FrameKey, variants: dict[int, int], tonemap: str, estimator: Estimator
                ) -> list[dict]:
    """Every (spp, variant) item of one frame: model-space arrays, float32."""
    sm = store.scene_manifest(key.scene)
    n, total = int(sm["stack_spp"]), int(sm["stacks"])
    needed = sorted({i for s, v in variants.items() for j in range(v) for i in variant_stacks(s, n, j, total)})
    images = {i: store.read_image(key.scene, key.frame, stack_name(i))[0] for i in needed}
    rotation = frame_rotation(store, key)
    items = []
    for spp, count in sorted(variants.items()):
        for v in range(count):
            buffers = combine_stacks([images[i] for i in variant_stacks(spp, n, v, total)], n)
            est, parts = estimator(buffers)
            noisy, aux = model_inputs(buffers, spp, rotation, tonemap, parts)
            items.append({"spp": spp, "noisy": noisy, "aux": aux,
                          "image": noisy if est is None else to_planar(est, tonemap)})
    return items


def build_pack(store: Store, keys: list[FrameKey], out: Path, tonemap: str = "log", estimator: Estimator | None = None,
               variants: dict[int, int] | None = None, quiet: bool = False, estimate_id: str = "") -> dict:
    """Write the pack of ``keys`` to ``out`` (atomically) and return its header. ``estimate_id`` names
    the estimator's weights (the Isik network's SHA-256), so a pack made with others is rebuilt."""
    estimator = estimator or Estimator()
    if not keys:
        raise StoreError(f"{store.root}: no frames to pack")
    sm = store.scene_manifest(keys[0].scene)
    variants = fit_variants(variants or PACK_VARIANTS, int(sm["stack_spp"]), int(sm["stacks"]))
    if not variants:
        raise StoreError(f"{store.root}: its stacks cannot pool any of the sample counts {sorted(PACK_VARIANTS)}")
    arrays: dict[str, list] = {"noisy": [], "aux": [], "image": [], "frame": [], "spp": []}
    targets = []
    for f, key in enumerate(progress(keys, desc=f"pack {out.name}", unit="frame", disable=quiet)):
        gt = store.read_image(key.scene, key.frame, "gt_clean", buffers=["color"])[0]["color"]
        targets.append(to_planar(gt, tonemap))
        for item in frame_items(store, key, variants, tonemap, estimator):
            for name in ("noisy", "aux", "image"):
                arrays[name].append(item[name])
            arrays["frame"].append(f)
            arrays["spp"].append(item["spp"])
    tensors = {name: torch.from_numpy(np.stack(arrays[name])).half() for name in ("noisy", "aux", "image")}
    tensors["target"] = torch.from_numpy(np.stack(targets)).half()
    tensors["frame"] = torch.tensor(arrays["frame"], dtype=torch.int32)
    tensors["spp"] = torch.tensor(arrays["spp"], dtype=torch.int32)
    header = {"format": FORMAT, "frames": [str(k) for k in keys], "aux_channels": aux_names(estimator.kind),
              "tonemap": tonemap, "estimate": estimator.kind, "estimate_id": estimate_id,
              "variants": {str(s): v for s, v in variants.items()}, "store": str(store.root)}
    out.parent.mkdir(parents=True, exist_ok=True)
    save_safetensors(out, tensors, {"format": FORMAT, "header": json.dumps(header)})
    return header


def read_header(path: Path) -> dict:
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
    except Exception as exc:
        raise StoreError(f"{path}: not a readable pack ({type(exc).__name__}: {exc})") from None
    if meta.get("format") != FORMAT:
        raise StoreError(f"{path}: not a {FORMAT} file")
    return json.loads(meta["header"])


class PackPairs(Dataset):
    """``DenoisePairs``'s items from a pack: random (frame, spp, variant) items, random crops and flips
    in training (``crop`` set), whole frames in order otherwise. Items float32, keys noisy, aux,
    target, image. ``spp_choices`` limits which of the pack's sample counts are drawn."""

    def __init__(self, path: Path, crop: int | None, crops_per_item: int = 1, seed: int = 0,
                 spp_choices: list[int] | None = None, tonemap: str = "log", estimate: str = "none",
                 augment: bool = True):
        from safetensors.torch import load_file

        self.path = Path(path)
        header = read_header(self.path)
        for key, want in (("aux_channels", aux_names(estimate)), ("tonemap", tonemap), ("estimate", estimate)):
            if header[key] != want:
                raise StoreError(f"{self.path}: pack made with another {key} ({header[key]!r}, this run wants "
                                 f"{want!r}); rebuild it with `python -m pipeline pack`")
        self.header = header
        self.t = load_file(str(self.path))
        spp = self.t["spp"].tolist()
        wanted = set(spp) if spp_choices is None else {int(s) for s in spp_choices}
        self.index = [i for i, s in enumerate(spp) if s in wanted]
        if not self.index:
            raise StoreError(f"{self.path}: no items at spp {sorted(wanted)} (pack has {sorted(set(spp))})")
        self.crop, self.per, self.seed, self.do_augment = crop, int(crops_per_item) if crop else 1, int(seed), augment
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.index) * self.per

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        i = self.index[index // self.per]
        frame = int(self.t["frame"][i])
        arrays = [self.t["noisy"][i].float().numpy(), self.t["aux"][i].float().numpy(),
                  self.t["target"][frame].float().numpy(), self.t["image"][i].float().numpy()]
        if self.crop is not None:
            rng = np.random.default_rng([self.seed, self.epoch, index])
            arrays = random_crop(arrays, self.crop, rng)
            if self.do_augment:
                arrays = augment(arrays, bool(rng.integers(2)), bool(rng.integers(2)), int(rng.integers(4)),
                                 aux_index=1)
        return {k: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
                for k, a in zip(("noisy", "aux", "target", "image"), arrays)}


def pack_path(runs: str | Path, split: str, estimate: str) -> Path:
    return Path(runs) / "pack" / f"{split}_{estimate.replace('+', '_')}.safetensors"


def ensure_pack(store: Store, keys: list[FrameKey], path: Path, tonemap: str, estimator: Estimator,
                quiet: bool = False, estimate_id: str = "") -> Path:
    """``path`` if it holds exactly ``keys`` in this layout and estimate, else (re)build it."""
    if path.exists():
        try:
            h = read_header(path)
            if (h["frames"] == [str(k) for k in keys] and h["aux_channels"] == aux_names(estimator.kind)
                    and h["tonemap"] == tonemap and h["estimate"] == estimator.kind
                    and h.get("estimate_id", "") == estimate_id):
                return path
        except (StoreError, KeyError, json.JSONDecodeError):
            pass
    build_pack(store, keys, path, tonemap, estimator, quiet=quiet, estimate_id=estimate_id)
    return path
