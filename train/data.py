"""The data: training packs and crops, and where a training run's frames come from (``StoreSource``); the
network's input encoding itself is ``train.model.inputs``.

**Pack** (``ensure_pack``): the store decoded once: per frame and (spp, variant) of
``PACK_VARIANTS`` (disjoint stack subsets), ``x`` and
``cond`` in float16 with the exposure, and GT_clean per frame in float32 HDR. ``Crops`` draws
training items from it: a random crop, OIDN's augmentation (flips, transposes, one permutation
of the colour channels for every colour-like channel and the target, one of the normal axes) and
the group dropout; the target is PU(GT_clean × the item's exposure), the space of OIDN's output. It is
built a scene at a time (``<pack>.parts/``), so a killed build resumes with the scenes it finished.

A **history pack** (``diffusion.history``, ``<split>_oidn_base[_calb]_history``) holds only the frames whose
previous frame (``FrameKey.previous``: t − 1, t 0-based) has gt_clean too, each as ``train.history`` serves it:
its input averaged over the frames before and after it (``eval.temporal_window``, ``eval.temporal_gate``,
``eval.temporal_ahead``) and the
history channels (OIDN's output of frame t − 1's input, on the same stacks, warped into frame t); its crops
lose the history with ``diffusion.history_dropout``.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch.utils.data import Dataset

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.exr import StoreError
from mcdenoise.pipeline.progress import progress
from mcdenoise.pipeline.weights import save_safetensors

from .model import ALIGNMENT, GROUPS, cond_layout, cond_names, groups, inputs, reads_history, to_pu

# The store is imported where it is read: ``denoise --exr`` encodes a frame without one.
if TYPE_CHECKING:
    from mcdenoise.pipeline.store import FrameKey, Store

FORMAT = "mcdenoise-oidn-pack"
# what a history pack's previous outputs are (``train.history``) and how they were read into the frame
# (``motion.warp_previous``): a pack with other histories is built again
HISTORY_SOURCE = "oidn_prefilter, catmull_rom on x/(1+x)"
DROPOUT = 0.15     # probability that a training item lacks a group (each group on its own)
_COLOURS = ("color", "albedo", *schema.RADIANCE_COMPONENTS)
# Noise realizations per frame in a pack, by spp: disjoint subsets of the store's stacks
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
    from mcdenoise.pipeline.store import poolable

    out = {}
    for spp, count in variants.items():
        if poolable(spp, stack_spp, stacks):
            n = min(int(count), stacks // (spp // stack_spp))
            if n > 0:
                out[int(spp)] = n
    return out


# ---- the pack ----------------------------------------------------------------------------------


def pack_path(runs: str | Path, split: str, clean_aux: bool = False, history: bool = False) -> Path:
    """``<runs>/pack/<split>_oidn_base[_calb][_history].safetensors`` (``_calb``: OIDN's input with prefiltered
    aux, for a ``_calb_cnrm`` base; ``_history``: frames with their history, for a model that reads the past)."""
    return (Path(runs) / "pack" /
            f"{split}_oidn_base{'_calb' if clean_aux else ''}{'_history' if history else ''}.safetensors")


def pack_keys(keys: list[FrameKey], history: bool) -> list[FrameKey]:
    """The frames a pack holds: all of ``keys``, or with history those whose previous frame is among them."""
    return list(_previous_frames(keys, history)) if history else list(keys)


def _previous_frames(keys: list[FrameKey], history: bool) -> dict:
    """``train.history.previous_frames`` with history, else {}: the motion code is read only where it is used."""
    if not history:
        return {}
    from .history import previous_frames
    return previous_frames(keys)


def _sequence_inputs(store: Store, window: tuple):
    """``train.history.SequenceInputs`` of ``store`` averaging over ``window`` = (frames, gate, frames ahead)."""
    from .history import SequenceInputs
    return SequenceInputs(store, *window)


def input_record(window: tuple) -> str | None:
    """How a history pack's input is averaged, for its metadata and the run's fingerprint (a pack averaged
    otherwise is built again); None for a window of 1 frame and none ahead, the input as packs had it before
    averaging."""
    from mcdenoise.pipeline.temporal import describe_averaging
    frames, gate, ahead = window
    return describe_averaging(frames, ahead, gate)


def build_pack(store: Store, keys: list[FrameKey], path: Path, quiet: bool = False, clean_aux: bool = False,
               history: bool = False, window: tuple = (1, None, 0)) -> Path:
    """Decode ``keys`` once into the pack at ``path`` (written atomically); ``clean_aux`` as ``inputs``;
    ``history``: the frames of ``keys`` whose previous frame is among them (``pack_keys``), each as
    ``train.history.SequenceInputs`` serves it (input averaged over ``window`` = (frames, gate, frames ahead),
    history on the same stacks).

    Each scene's frames are decoded into a part of their own beside the pack (``<pack>.parts/<scene>``; a
    scene's frames are one walk along its move, scenes are independent): a killed build keeps its finished
    parts and the next one reuses those that still hold what is asked; the parts go once the pack is written.
    (A large store's pack takes most of an hour on 2 cores.)"""
    import shutil

    scenes = _by_scene(pack_keys(keys, history))
    keys = _pack_order(scenes)
    if not keys:
        raise StoreError(f"{store.root}: no frame with a previous frame for a history pack (diffusion.history "
                         "needs scenes of two or more frames with gt_clean)")
    parts = path.with_name(path.name + ".parts")
    jobs = [(ks, parts / f"{scene}.safetensors") for scene, ks in scenes.items()]
    todo = [(ks, part) for ks, part in jobs if not _matches(part, store, ks, clean_aux, history, window)]
    bar = progress(total=len(keys), initial=len(keys) - sum(len(ks) for ks, _ in todo), desc=f"pack {path.name}",
                   unit="frame", disable=quiet)
    for ks, part in todo:
        _build_part(store, ks, part, clean_aux, history, window)
        bar.update(len(ks))
    bar.close()
    tensors = _assemble(store, jobs)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_safetensors(path, tensors, {**_pack_meta(store, keys, clean_aux, history, window),
                                     "sizes": json.dumps([list(tensors["x"].shape[1:])])})
    shutil.rmtree(parts, ignore_errors=True)
    return path


def _pack_order(scenes: dict[str, list[FrameKey]]) -> list[FrameKey]:
    """A pack's frames: its scenes' frames, a scene after the other (``_by_scene``)."""
    return [k for ks in scenes.values() for k in ks]


def _by_scene(keys: list[FrameKey]) -> dict[str, list[FrameKey]]:
    """{scene: its frames of ``keys``}, in the order of ``keys``: a pack's order."""
    scenes: dict[str, list[FrameKey]] = {}
    for key in keys:
        scenes.setdefault(key.scene, []).append(key)
    return scenes


def _pack_meta(store: Store, frames: list[FrameKey], clean_aux: bool, history: bool, window: tuple) -> dict:
    """What a pack (or a part of one) was made of: a pack whose metadata differs is built again."""
    return {"format": FORMAT, "store": str(store.root), "frames": json.dumps([f"{k.scene}/{k.frame}" for k in frames]),
            "cond": json.dumps(cond_names(history)), "aux": _aux_kind(clean_aux),
            **({"history": HISTORY_SOURCE} if history else {}),
            **({"input": input_record(window)} if history and input_record(window) else {})}


def _matches(path: Path, store: Store, frames: list[FrameKey], clean_aux: bool, history: bool, window: tuple) -> bool:
    """Whether the pack or part at ``path`` holds ``frames`` (already ``pack_keys``) as they are asked for."""
    if not path.exists():
        return False
    from safetensors import safe_open
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
    want = _pack_meta(store, frames, clean_aux, history, window)
    return all(meta.get(k) == want.get(k) for k in ("format", "store", "frames", "cond", "aux", "history", "input"))


def _build_part(store: Store, keys: list[FrameKey], path: Path, clean_aux: bool, history: bool, window: tuple) -> None:
    """The part of one scene's ``keys`` (in order along its move) at ``path``, written atomically."""
    from mcdenoise.pipeline.store import combine_stacks, stack_name

    walks = _sequence_inputs(store, window) if history else None
    plan = [_frame_variants(store, key) for key in keys]
    count = sum(v for _, _, variants in plan for v in variants.values())
    # the items go straight into arrays of their final size, not into lists stacked at the end (twice the memory)
    arrays: dict[str, np.ndarray] = {}
    scales, spps, frames = [], [], []
    for i, (key, (n, total, variants)) in enumerate(zip(keys, plan)):
        need = sorted({s for spp, v in variants.items() for j in range(v) for s in variant_stacks(spp, n, j, total)})
        images = {s: store.read_image(key.scene, key.frame, stack_name(s))[0] for s in need}
        for spp, v in ((spp, v) for spp, c in sorted(variants.items()) for v in range(c)):
            stacks = variant_stacks(spp, n, v, total)
            buffers = combine_stacks([images[s] for s in stacks], n)
            if walks is not None:
                buffers = walks.of(key, tuple(stacks), lambda f, b=buffers, k=key, st=stacks: (
                    b if f == k.frame else store.read(k.scene, f, spp, stacks=st)))
            x, cond, scale = inputs(buffers, spp, clean_aux=clean_aux, history=history)
            _put(arrays, len(scales), count, store, key, x=x, cond=cond)
            scales.append(scale)
            spps.append(spp)
            frames.append(i)
        gt = store.read_image(key.scene, key.frame, "gt_clean", ["color"])[0]["color"]
        _put(arrays, i, len(keys), store, key, target=np.pad(np.moveaxis(gt, 2, 0), (
            (0, 0), (0, arrays["x"].shape[2] - gt.shape[0]), (0, arrays["x"].shape[3] - gt.shape[1]))))
    tensors = {"x": torch.from_numpy(arrays["x"]), "cond": torch.from_numpy(arrays["cond"]),
               "scale": torch.tensor(scales, dtype=torch.float32), "spp": torch.tensor(spps, dtype=torch.int32),
               "frame": torch.tensor(frames, dtype=torch.int32), "target": torch.from_numpy(arrays["target"])}
    path.parent.mkdir(parents=True, exist_ok=True)
    save_safetensors(path, tensors, _pack_meta(store, keys, clean_aux, history, window))


def _assemble(store: Store, jobs: list[tuple[list[FrameKey], Path]]) -> dict[str, torch.Tensor]:
    """The parts of ``jobs`` (each (its frames, its path)) as one pack's tensors, in order; each part is read
    into arrays of the pack's final size, so the pack is held once. ``frame`` counts across the parts."""
    from safetensors import safe_open

    shapes = []
    for _, part in jobs:
        with safe_open(str(part), framework="pt") as f:
            shapes.append({name: f.get_slice(name).get_shape() for name in f.keys()})
    out: dict[str, torch.Tensor] = {}
    rows = {name: 0 for name in shapes[0]}
    offset = 0
    for (ks, part), shape in zip(jobs, shapes):
        if shape["x"][1:] != shapes[0]["x"][1:]:
            raise StoreError(f"{store.root}: frame {ks[0]} is {shape['x'][3]}×{shape['x'][2]}, the pack's frames "
                             f"{shapes[0]['x'][3]}×{shapes[0]['x'][2]}; a pack needs one size")
        for name, tensor in load_pack(part).items():
            if name not in out:
                total = sum(s[name][0] for s in shapes)
                out[name] = torch.empty((total, *tensor.shape[1:]), dtype=tensor.dtype)
            out[name][rows[name]:rows[name] + len(tensor)] = tensor + offset if name == "frame" else tensor
            rows[name] += len(tensor)
        offset += len(ks)
    return out


def _frame_variants(store: Store, key: FrameKey) -> tuple[int, int, dict[int, int]]:
    """(stack spp, stacks, {spp: noise realizations}) of ``key``'s scene in a pack."""
    sm = store.scene_manifest(key.scene)
    n, total = int(sm["stack_spp"]), int(sm["stacks"])
    return n, total, fit_variants(PACK_VARIANTS, n, total)


def _put(arrays: dict[str, np.ndarray], row: int, rows: int, store: Store, key: FrameKey, **values) -> None:
    """``arrays[name][row] = value`` for each value, the array allocated at ``rows`` rows by its first value
    (float16 for the inputs, float32 for the target); StoreError naming the frame if its size differs."""
    for name, value in values.items():
        if name not in arrays:
            arrays[name] = np.empty((rows, *value.shape), np.float32 if name == "target" else np.float16)
        if arrays[name].shape[1:] != value.shape:
            raise StoreError(f"{store.root}: frame {key} is {value.shape[-1]}×{value.shape[-2]}, "
                             f"the pack's frames {arrays[name].shape[-1]}×{arrays[name].shape[-2]}; a pack needs "
                             "one size")
        arrays[name][row] = value


def _aux_kind(clean_aux: bool) -> str:
    return "prefiltered" if clean_aux else "rendered"


def ensure_pack(store: Store, keys: list[FrameKey], path: Path, quiet: bool = False, clean_aux: bool = False,
                history: bool = False, window: tuple = (1, None, 0)) -> Path:
    """The pack of ``keys`` at ``path``, built if missing or made from other frames, another layout, other aux
    or (with history) another averaging."""
    if pack_ready(store, keys, path, clean_aux, history, window):
        return path
    return build_pack(store, keys, path, quiet, clean_aux, history, window)


def pack_ready(store: Store, keys: list[FrameKey], path: Path, clean_aux: bool = False, history: bool = False,
               window: tuple = (1, None, 0)) -> bool:
    """Whether the pack at ``path`` is ``keys``'s as ``ensure_pack`` would build it."""
    return _matches(path, store, _pack_order(_by_scene(pack_keys(keys, history))), clean_aux, history, window)


def load_pack(path: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file
    return load_file(str(path))


def concat_packs(packs: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """One pack of several (each item keeps its own frame's target)."""
    if len(packs) == 1:
        return packs[0]
    offsets = np.cumsum([0] + [len(p["target"]) for p in packs[:-1]])
    out = {k: torch.cat([p[k] for p in packs]) for k in packs[0] if k != "frame"}
    out["frame"] = torch.cat([p["frame"] + int(o) for p, o in zip(packs, offsets)])
    return out


# ---- training items ----------------------------------------------------------------------------


def _channel_groups(aux: int, history: bool = False) -> tuple[list[list[int]], list[list[int]]]:
    """(RGB triples of colour-like channels, XYZ triples of normals) as indices into x ⊕ cond."""
    names = [f"x.{i}" for i in range(3 + 3 * aux)] + cond_names(history)
    colours = [[0, 1, 2]] + ([[3, 4, 5]] if aux >= 1 else [])
    normals = [[6, 7, 8]] if aux >= 2 else []
    for key in _COLOURS:
        colours.append([names.index(f"{key}.{c}") for c in "RGB"])
    if history:     # the previous output is a colour: its channels are permuted with the others
        colours.append([names.index(f"history.{c}") for c in "RGB"])
    normals.append([names.index(f"normal.{c}") for c in "XYZ"])
    return colours, normals


class EpochItems(Dataset):
    """``per_frame`` items per frame of ``frames``, item ``index`` of an epoch drawn from
    ``default_rng([seed, epoch, index])``: the same batches with any number of loader workers, and a resumed run
    draws what an uninterrupted one would. The crop datasets of the denoiser and of the baselines share it."""

    frames: list
    per_frame: int
    seed: int
    epoch: int = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.frames) * self.per_frame

    def item_rng(self, index: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.epoch, index])


class Crops(EpochItems):
    """Random crops of a pack, augmented; item ``index`` of an epoch from ``default_rng([seed, epoch, index])``.

    Items: ``x`` (OIDN's input), ``cond``, ``target`` (PU of GT_clean at the item's exposure), ``scale``, ``spp``.
    A history pack's items lose their history with probability ``history_dropout``."""

    def __init__(self, pack: dict[str, torch.Tensor], crop: int, per_frame: int, seed: int, spps: list[int] | None = None,
                 augment: bool = True, dropout: float = DROPOUT, history_dropout: float = 0.0):
        self.pack, self.crop, self.per_frame, self.seed = pack, int(crop), int(per_frame), int(seed)
        self.augment, self.dropout, self.epoch = augment, float(dropout), 0
        self.history = reads_history(cond_layout(pack["cond"].shape[1]))
        self.drop = {g: float(history_dropout) if g == "history" else self.dropout for g in groups(self.history)}
        keep = torch.ones(len(pack["spp"]), dtype=torch.bool) if not spps else torch.isin(pack["spp"], torch.tensor(spps))
        self.items = torch.nonzero(keep).flatten().tolist()
        self.frames = sorted({int(pack["frame"][i]) for i in self.items})
        self.by_frame = {f: [i for i in self.items if int(pack["frame"][i]) == f] for f in self.frames}
        aux = (pack["x"].shape[1] - 3) // 3
        self.colours, self.normals = _channel_groups(aux, self.history)
        names = cond_names(self.history)
        nx = pack["x"].shape[1]
        self.groups = {g: [nx + names.index(f"has.{g}")] + [nx + j for j, n in enumerate(names)
                                                            if n.split(".")[0] in GROUPS[g] or n in GROUPS[g]]
                       for g in groups(self.history)}
        H, W = pack["x"].shape[-2:]
        if self.crop > min(H, W) or self.crop % ALIGNMENT:
            raise StoreError(f"diffusion.crop {self.crop}: must be a multiple of {ALIGNMENT} up to the frames' "
                             f"{min(H, W)} (set diffusion.crop={min(H, W) // ALIGNMENT * ALIGNMENT})")

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = self.item_rng(index)
        options = self.by_frame[self.frames[index // self.per_frame]]
        i = options[int(rng.integers(len(options)))]
        p = self.pack
        H, W = p["x"].shape[-2:]
        c = self.crop
        y, x0 = int(rng.integers(0, H - c + 1)), int(rng.integers(0, W - c + 1))
        win = (slice(None), slice(y, y + c), slice(x0, x0 + c))
        full = torch.cat([p["x"][i][win], p["cond"][i][win]]).float()
        target = p["target"][int(p["frame"][i])][win].float()
        if self.augment:
            full, target = self._augment(full, target, rng)
        for g, idx in self.groups.items():
            if rng.random() < self.drop[g]:
                full[idx] = 0.0
        nx = p["x"].shape[1]
        scale = float(p["scale"][i])
        return {"x": full[:nx].contiguous(), "cond": full[nx:].contiguous(),
                "target": to_pu(target * scale), "scale": torch.tensor(scale), "spp": p["spp"][i].long()}

    def _augment(self, full: torch.Tensor, target: torch.Tensor, rng: np.random.Generator):
        colour, axes = rng.permutation(3).tolist(), rng.permutation(3).tolist()
        src = list(range(full.shape[0]))
        for g in self.colours:
            for k in range(3):
                src[g[k]] = g[colour[k]]
        for g in self.normals:
            for k in range(3):
                src[g[k]] = g[axes[k]]
        full, target = full[src], target[colour]
        if rng.integers(2):
            full, target = full.flip(-1), target.flip(-1)
        if rng.integers(2):
            full, target = full.flip(-2), target.flip(-2)
        if rng.integers(2):
            full, target = full.transpose(-1, -2), target.transpose(-1, -2)
        return full.contiguous(), target.contiguous()


# ---- where a training run's frames come from --------------------------------------------------


class StoreSource:
    """The data of a config's store: the train split as the pack (``train.data``), the first
    ``val_frames`` val frames whole, each at the run's smallest, middle and largest sample count."""

    def __init__(self, cfg: Config, network: str | None = None, history: bool | None = None):
        """``network``: the base's (default ``diffusion.base_network``); a ``_calb_cnrm`` one reads prefiltered aux.
        ``history`` (default ``diffusion.history``): packs and val frames with their history."""
        from mcdenoise.pipeline.store import Store

        self.cfg, self.store = cfg, Store(cfg.store)
        from .oidn import clean_aux
        self.clean_aux = clean_aux(network or cfg.diffusion.base_network)
        self.history = cfg.diffusion.history if history is None else bool(history)
        # a model that reads the past trains on the input the temporal methods give it (train.history)
        self.window = (cfg.eval.temporal_window, cfg.eval.temporal_gate or None, cfg.eval.temporal_ahead)
        self.train_keys, self.val_keys = self.store.training_frames()
        self.extra = [(store, store.training_frames()[0]) for store in map(Store, cfg.diffusion.extra_stores)]

    def spps(self, spp) -> list[int]:
        return self.store.spp_choices(spp)

    def train_pack(self, quiet: bool, build: bool = True) -> dict[str, torch.Tensor]:
        """The train packs of the store and of ``diffusion.extra_stores`` as one, built where missing; ``build``
        False waits for another process to write them instead. (Under torchrun rank 0 builds and the other
        ranks wait: two builds of one pack would remove each other's parts.)"""
        packs = []
        for i, (store, keys) in enumerate([(self.store, self.train_keys), *self.extra]):
            path = self.pack_path("train" if i == 0 else f"train_extra{i - 1}")
            if build:
                ensure_pack(store, keys, path, quiet, self.clean_aux, self.history, self.window)
            else:
                while not pack_ready(store, keys, path, self.clean_aux, self.history, self.window):
                    time.sleep(5)
            packs.append(load_pack(path))
        return concat_packs(packs)

    def pack_path(self, split: str) -> Path:
        return pack_path(self.cfg.runs, split, self.clean_aux, self.history)

    def val_items(self, spps: list[int], frames: int) -> list[dict]:
        items = []
        walks = _sequence_inputs(self.store, self.window) if self.history else None
        for key in pack_keys(self.val_keys, self.history)[:frames]:
            ref = self.store.read_image(key.scene, key.frame, "gt_clean", ["color"])[0]["color"]
            for spp in sorted({spps[0], spps[len(spps) // 2], spps[-1]}):
                buffers = self.store.read(key.scene, key.frame, spp)
                if walks is not None:   # the first stacks of every frame, as a sequence is evaluated
                    buffers = walks.of(key, (spp,), lambda f, k=key, s=spp: self.store.read(k.scene, f, s))
                x, cond, scale = inputs(buffers, spp, clean_aux=self.clean_aux, history=self.history)
                items.append({"x": torch.from_numpy(x)[None], "cond": torch.from_numpy(cond)[None], "scale": scale,
                              "ref": ref, "spp": spp})
        return items


def cmd_pack(cfg: Config, splits: list[str], quiet: bool = False) -> int:
    """Write the training packs of ``splits`` (``train.data.ensure_pack``) for the configured base's inputs."""
    source = StoreSource(cfg)
    for split in splits:
        keys = source.store.frames_with(split)
        if not keys:
            raise StoreError(f"{source.store.root}: no {split} frame with gt_clean; run `make gt-clean`")
        path = ensure_pack(source.store, keys, source.pack_path(split), quiet, source.clean_aux, source.history,
                           source.window)
        print(f"pack {split}: {len(pack_keys(keys, source.history))} frames -> {path} ({path.stat().st_size / 2**20:.1f} MiB)", flush=True)
    return 0
