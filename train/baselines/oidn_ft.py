"""``oidn_ft``: OIDN's own network fine-tuned on the store, from its pretrained weights.

    make train MODEL=oidn_ft SPP=any     → runs/<...>/oidn_ft_<network>/   (one model for 4 … 64 spp)

The run reads top to bottom in ``OIDNFineTune``: the network is OIDN's (``train.model``,
weights from pyoidn's library or ``oidn.weights``), the data are random crops of the train
split at a random sample count (``FrameCrops``), the step is one Adam update of L1 (or L1 + SSIM)
in OIDN's output space, and validation scores whole val frames at every sample count, by PSNR
against GT_clean (the best epoch is kept). What keeps the prior's generality (measured in
``docs/oidn.md``), each a config key of ``oidn_ft``:

- ``augment``: OIDN's own augmentation (colour-channel and normal-channel permutations, flips,
  transposes), so the network cannot learn the randomizer's colours or orientations;
- ``l2sp``: an L2-SP penalty toward OIDN's weights;
- ``distill``: part of each batch is a changed input (colours permuted and rescaled, half
  resolution, another frame's noise level) whose target is stock OIDN's output on it;
- ``trainable``: all weights, the decoder, the biases only, or the layers at the finest
  resolutions (``fine``, ``fine_levels``: 4 leaves only the bottleneck OIDN's);
- ``blend``: used or exported, the weights are OIDN's plus ``blend`` × what training changed.

Files of the run folder: ``model.safetensors`` + ``model.json`` (the best epoch: float32 UNet
weights, the network name, the prior's sha256, the validation scores beside stock OIDN's),
``last.safetensors`` (resume; ``clean.fit``), ``train.json`` and ``loss.png``.
"""
from __future__ import annotations

import copy
import hashlib
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader

from mcdenoise.clean.fit import Task, apply_update, fit
from mcdenoise.pipeline import config as config_mod, weights
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.exr import atomic_write_json
from mcdenoise.pipeline.figures import plot_curves
from mcdenoise.pipeline.metrics import PSNR_CEILING, psnr
from mcdenoise.pipeline.progress import progress
from mcdenoise.pipeline.store import FrameKey, Store, stack_name
from mcdenoise.pipeline.weights import read_tza, write_tza
from mcdenoise.train import oidn

from ..data import EpochItems
from ..model import UNet, autoexposure, network_input, to_pu, unet_denoise

FORMAT = weights.FORMATS["oidn_ft"]
AUX = oidn.network_aux("rt_hdr_alb_nrm")


# ---- data --------------------------------------------------------------------------------------


class Frame:
    """One store frame in memory: its stacks' colour and aux (K, H, W, 3) and its training target (H, W, 3):
    GT_clean, or the raw GT1 (``oidn_ft.target``). ``clean_aux``: each stack's albedo and normal prefiltered
    by OIDN's aux networks, once (a pooled frame's are then the mean of its stacks', close to the prefilter
    of their mean that validation and inference run, which every training item would have to run again)."""

    def __init__(self, store: Store, key: FrameKey, aux: tuple[str, ...], target: str = "gt_clean",
                 clean_aux: bool = False):
        sm = store.scene_manifest(key.scene)
        self.key, self.stack_spp = key, int(sm["stack_spp"])
        stacks = [store.read_image(key.scene, key.frame, stack_name(k), ["color", *aux])[0]
                  for k in range(int(sm["stacks"]))]
        self.color = np.stack([s["color"] for s in stacks]).astype(np.float32)
        # aux buffers a reader left out (e.g. a constant one) are what the schema says: zeros
        self.aux = {a: np.stack([s.get(a, np.zeros_like(s["color"])) for s in stacks]).astype(np.float16) for a in aux}
        if clean_aux:
            pre = [oidn.prefilter_aux(s["albedo"], s["normal"]) for s in stacks]
            self.aux = {a: np.stack([p[i] for p in pre]).astype(np.float16) for i, a in enumerate(("albedo", "normal"))}
        self.target = store.read_image(key.scene, key.frame, target, ["color"])[0]["color"].astype(np.float32)

    def pooled(self, stacks: list[int]) -> dict[str, np.ndarray]:
        """The frame at len(stacks) × stack_spp samples: the mean of those stacks (as ``Store.read``)."""
        out = {"color": self.color[stacks].mean(0)}
        out.update({a: v[stacks].astype(np.float32).mean(0) for a, v in self.aux.items()})
        return out


def _augment(images: dict[str, np.ndarray], rng: np.random.Generator) -> dict[str, np.ndarray]:
    """OIDN's training augmentation on (H, W, 3) images: one colour permutation for colour, albedo and
    target, a permutation of the normal axes, flips and a transpose (the same for every image)."""
    colour, axes = rng.permutation(3), rng.permutation(3)
    flip_y, flip_x, transpose = (bool(b) for b in rng.integers(0, 2, 3))
    out = {}
    for name, im in images.items():
        im = im[..., axes] if name == "normal" else im[..., colour]
        im = im[::-1] if flip_y else im
        im = im[:, ::-1] if flip_x else im
        out[name] = np.ascontiguousarray(im.transpose(1, 0, 2) if transpose else im)
    return out


def _unlike(images: dict[str, np.ndarray], rng: np.random.Generator, min_side: int) -> dict[str, np.ndarray]:
    """A frame unlike the training set's: per-channel gains on the light (colour and ``target``, when there is
    one, alike; albedo is reflectance and stays) and, half the time, the frame at half resolution when that
    is still at least ``min_side`` pixels (objects half as large, the noise averaged 2×2). With the teacher's
    output as the target (``distill``) the gains also tint the albedo, kept in [0, 1]."""
    gains = np.exp(rng.normal(0.0, 0.6, 3)).astype(np.float32)
    out = dict(images)
    for name in ("color", "target"):
        if name in images:
            out[name] = images[name] * gains
    if "albedo" in images and "target" not in images:
        out["albedo"] = np.clip(images["albedo"] * gains / gains.max(), 0, 1)
    H, W = images["color"].shape[:2]
    if min(H, W) // 2 >= min_side and rng.random() < 0.5:
        out = {k: v[:H // 2 * 2, :W // 2 * 2].reshape(H // 2, 2, W // 2, 2, 3).mean((1, 3)) for k, v in out.items()}
        if "normal" in out:
            out["normal"] = out["normal"] / np.maximum(np.linalg.norm(out["normal"], axis=2, keepdims=True), 1e-6)
    return out


class FrameCrops(EpochItems):
    """Training items: a crop of a train frame at a random sample count, as OIDN's network reads it.

    Item ``index`` of an epoch draws from ``default_rng([seed, epoch, index])`` (resumes exactly):
    the sample count (of ``spps``), which stacks make it, the crop and the augmentation. The
    exposure is OIDN's autoexposure of the whole pooled frame, as at inference. ``distill`` of
    the items are changed inputs (``_unlike``) flagged for the teacher's target."""

    def __init__(self, frames: list[Frame], spps: list[int], crop: int, crops_per_frame: int, seed: int,
                 aux: tuple[str, ...], augment: bool, distill: float, diversify: float = 0.0):
        self.frames, self.spps, self.crop, self.per_frame = frames, spps, crop, crops_per_frame
        self.seed, self.aux, self.augment, self.distill, self.epoch = seed, aux, augment, distill, 0
        self.diversify = diversify

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = self.item_rng(index)
        frame = self.frames[index // self.per_frame]
        spp = self.spps[int(rng.integers(len(self.spps)))]
        k = spp // frame.stack_spp
        images = frame.pooled(sorted(rng.choice(len(frame.color), size=k, replace=False).tolist()))
        teacher = bool(rng.random() < self.distill)
        if teacher:
            images = _unlike(images, rng, self.crop)
            images["target"] = np.zeros_like(images["color"])     # replaced by the teacher's output
        else:
            images["target"] = frame.target
            if rng.random() < self.diversify:
                images = _unlike(images, rng, self.crop)
        scale = autoexposure(images["color"])
        H, W = images["color"].shape[:2]
        c = self.crop
        y, x = int(rng.integers(0, H - c + 1)), int(rng.integers(0, W - c + 1))
        images = {n: im[y:y + c, x:x + c] for n, im in images.items()}
        if self.augment:
            images = _augment(images, rng)
        net_in = network_input(images["color"], *(images[a] for a in self.aux), scale=scale)[0]
        target = to_pu(torch.from_numpy(images["target"]).permute(2, 0, 1) * scale)
        return {"input": net_in, "target": target, "teacher": torch.tensor(teacher)}


def ssim_loss(a: torch.Tensor, b: torch.Tensor, window: int = 7) -> torch.Tensor:
    """1 − SSIM of (B, 3, H, W) images in [0, 1]-ish PU space (uniform window; OIDN's kit uses MS-SSIM,
    whose coarse scales do not fit 64² crops)."""
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mu_a, mu_b = F.avg_pool2d(a, window, 1), F.avg_pool2d(b, window, 1)
    var_a = F.avg_pool2d(a * a, window, 1) - mu_a ** 2
    var_b = F.avg_pool2d(b * b, window, 1) - mu_b ** 2
    cov = F.avg_pool2d(a * b, window, 1) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return 1.0 - s.mean()


RELATIVE_FLOOR = 1e-4   # PU-space L1 added to each crop's normaliser (stock OIDN's error is ~4e-3 on average)


def relative_l1(out: torch.Tensor, target: torch.Tensor, stock: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """Mean over crops of L1(out, target) / (L1(stock OIDN, target) + floor): each crop counts by its gain
    over OIDN, so the few crops OIDN gets badly wrong cannot outweigh the many it gets right (where a
    change costs as much). Distillation crops (``teacher``), whose target is OIDN's own output, are
    divided by the mean normaliser of the others."""
    err = (out - target).abs().flatten(1).mean(1)
    with torch.no_grad():
        norm = (stock - target).abs().flatten(1).mean(1) + RELATIVE_FLOOR
        own = ~teacher
        typical = norm[own].mean() if bool(own.any()) else torch.tensor(4e-3, device=norm.device)
        norm = torch.where(teacher, typical, norm)
    return (err / norm).mean()


def l2sp_penalty(model: torch.nn.Module, reference: dict[str, torch.Tensor]) -> torch.Tensor:
    """Mean over the weight tensors of |w − w_ref|² / |w_ref|² (each layer's relative change, squared)."""
    terms = [((p - reference[n]) ** 2).sum() / (reference[n] ** 2).sum().clamp(min=1e-12)
             for n, p in model.named_parameters() if p.requires_grad]
    return torch.stack(terms).mean()


def lr_at(step: int, total: int, lr: float, lr_end: float, warmup: int) -> float:
    """Linear warm-up from 0 over ``warmup`` steps, then a cosine from ``lr`` to ``lr_end`` at ``total``."""
    if step < warmup:
        return lr * (step + 1) / warmup
    t = min(1.0, (step - warmup) / max(1, total - warmup))
    return lr_end + 0.5 * (lr - lr_end) * (1 + math.cos(math.pi * t))


def trainable_parameters(net: UNet, which: str, fine_levels: int = 4) -> list[torch.nn.Parameter]:
    """Set ``requires_grad`` by ``oidn_ft.trainable`` (and ``fine_levels``) and return the trained parameters."""
    level = net.layout.level
    for name, p in net.named_parameters():
        layer = name.split(".")[0]
        p.requires_grad_(which == "all" or (which == "decoder" and layer in net.layout.decoder)
                         or (which == "bias" and name.endswith(".bias"))
                         or (which == "fine" and level[layer] < fine_levels))
    return [p for p in net.parameters() if p.requires_grad]


# ---- the run -----------------------------------------------------------------------------------


def prior(cfg: Config) -> tuple[UNet, str]:
    """OIDN's pretrained network for ``oidn_ft.network`` and the sha256 of its TZA bytes."""
    name = cfg.oidn_ft.network
    blob = oidn.weights_blob(name, oidn.weights_source(name, cfg.oidn.weights))
    return UNet.from_tza(read_tza(blob, name)), hashlib.sha256(blob).hexdigest()


class OIDNFineTune(Task):
    """OIDN's network, fine-tuned on the store's train split (see the module docstring)."""

    minimize = False          # validation PSNR
    validate_initial = True   # epoch 0 is stock OIDN: a candidate the run must beat

    def __init__(self, cfg: Config, spp="any"):
        o = self.o = cfg.oidn_ft
        self.cfg, self.store = cfg, Store(cfg.store)
        self.train_keys, self.val_keys = self.store.training_frames()
        self.spps = self.store.spp_choices(spp)
        self.aux = oidn.network_aux(o.network)
        self.clean_aux = oidn.clean_aux(o.network)    # OIDN's final-frame mode: prefiltered aux
        self.folder = config_mod.run_dir(cfg, "oidn_ft")
        self.name, self.epochs, self.time_budget_s, self.nan_limit = self.folder.name, o.epochs, o.time_budget_s, o.nan_limit
        self.device = config_mod.pick_device(o.device)

        # The model: OIDN's network, and a frozen copy of it (the teacher, and L2-SP's reference).
        torch.manual_seed(cfg.seed)
        self.net, self.prior_sha = prior(cfg)
        self.net.to(self.device)
        self.teacher = copy.deepcopy(self.net).eval().requires_grad_(False)
        self.reference = {n: p.detach().clone() for n, p in self.teacher.named_parameters()}
        self.params = trainable_parameters(self.net, o.trainable, o.fine_levels)
        self.state, self.optimizers = self.net, torch.optim.AdamW(self.params, lr=o.lr, weight_decay=o.weight_decay)
        self.steps_per_epoch = self._steps_per_epoch()
        self.total_steps = self.steps_per_epoch * o.epochs
        self.fmt = FORMAT
        self.fingerprint = {"network": o.network, "prior_sha256": self.prior_sha, "spp": str(spp), "seed": cfg.seed,
                            **{k: getattr(o, k) for k in ("batch_size", "crop", "crops_per_frame", "epoch_steps",
                                                           "lr", "lr_end", "warmup_steps", "weight_decay", "grad_clip",
                                                           "loss", "l2sp", "distill", "diversify", "trainable", "augment",
                                                           "epochs")}}
        if o.target != "gt_clean":   # left out at its default: runs made before the key keep their fingerprint
            self.fingerprint["target"] = o.target
        if o.trainable == "fine":
            self.fingerprint["fine_levels"] = o.fine_levels
        self.output = str(self.folder / "model.safetensors")
        self.crops = self.val = None

    def _steps_per_epoch(self) -> int:
        steps = math.ceil(len(self.train_keys) * self.o.crops_per_frame / self.o.batch_size)
        return min(steps, self.o.epoch_steps) if self.o.epoch_steps else steps

    # ---- data
    def prepare(self) -> None:
        t = time.perf_counter()
        frames = [Frame(self.store, k, self.aux, self.o.target, self.clean_aux)
                  for k in progress(self.train_keys, desc=f"{self.name}: reading", unit="frame")]
        self.crops = FrameCrops(frames, self.spps, self.o.crop, self.o.crops_per_frame, self.cfg.seed, self.aux,
                                self.o.augment, self.o.distill, self.o.diversify)
        self.val = self._validation_items()
        print(f"{self.name}: {len(frames)} train frames at {self.spps} spp, {len(self.val)} validation images, "
              f"read in {time.perf_counter() - t:.1f} s", flush=True)

    def _validation_items(self) -> list[dict]:
        keys = self.val_keys[: self.o.val_frames] if self.o.val_frames else self.val_keys
        items = []
        for key in keys:
            ref = self.store.read_image(key.scene, key.frame, "gt_clean", ["color"])[0]["color"]
            for spp in self.spps:
                buf = self.store.read(key.scene, key.frame, spp, ["color", *self.aux])
                images = [buf["color"], *(buf.get(a, np.zeros_like(buf["color"])) for a in self.aux)]
                if self.clean_aux:
                    images[1:] = oidn.prefilter_aux(*images[1:])
                items.append({"images": images, "ref": ref, "spp": spp,
                              "stock": unet_denoise(self.teacher, *images, device=self.device)})
        return items

    def batches(self, epoch: int):
        self.crops.set_epoch(epoch)
        rng = np.random.default_rng([self.cfg.seed, epoch])
        order = rng.permutation(len(self.crops))[: self.steps_per_epoch * self.o.batch_size].tolist()
        self.net.train()
        return DataLoader(self.crops, batch_size=self.o.batch_size, sampler=order, num_workers=0)

    # ---- the step
    def step(self, batch: dict, epoch: int, index: int) -> tuple[dict, bool]:
        lr = lr_at(epoch * self.steps_per_epoch + index, self.total_steps, self.o.lr, self.o.lr_end,
                   self.o.warmup_steps)
        for group in self.optimizers.param_groups:
            group["lr"] = lr
        x, target, teacher = batch["input"], batch["target"], batch["teacher"]
        stock = None
        if bool(teacher.any()) or self.o.loss == "l1_relative":
            with torch.no_grad():
                stock = self.teacher(x)
            target = torch.where(teacher[:, None, None, None], stock, target)
        out = self.net(x)
        if self.o.loss == "l1_relative":
            loss = relative_l1(out, target, stock, teacher)
        else:
            loss = F.l1_loss(out, target)
        if self.o.loss == "l1_ssim":
            loss = 0.16 * loss + 0.84 * ssim_loss(out, target)
        terms = {"data": float(loss.detach())}
        if self.o.l2sp > 0:
            penalty = l2sp_penalty(self.net, self.reference)
            loss = loss + self.o.l2sp * penalty
            terms["l2sp"] = float(penalty.detach())
        return {"loss": float(loss.detach()), **terms, "lr": lr}, apply_update(loss, self.optimizers, self.params,
                                                                                self.o.grad_clip)

    def entry(self, epoch: int, kept: list[dict], skipped: int) -> dict:
        mean = {k: float(np.mean([t[k] for t in kept])) for k in (kept[0] if kept else {})}
        return {"epoch": epoch + 1, "train_loss": mean.pop("loss", None), "terms": mean, "skipped_steps": skipped}

    # ---- validation and files
    @torch.no_grad()
    def validate(self) -> dict | None:
        if not self.val:
            return None
        self.net.eval()
        rows = [(it["spp"], min(psnr(unet_denoise(self.net, *it["images"], device=self.device), it["ref"]),
                                PSNR_CEILING), min(psnr(it["stock"], it["ref"]), PSNR_CEILING)) for it in self.val]
        self.net.train()
        out = {"psnr": float(np.mean([r[1] for r in rows])), "oidn_psnr": float(np.mean([r[2] for r in rows])),
               "images": len(rows)}
        for spp in self.spps:
            sel = [r for r in rows if r[0] == spp]
            out[f"gain_spp{spp}"] = float(np.mean([r[1] - r[2] for r in sel]))
        return out

    def initial_entry(self) -> dict:
        return {"epoch": 0, "train_loss": None, "terms": {}, "skipped_steps": 0}

    def score(self, entry: dict) -> float | None:
        return entry["val"]["psnr"] if entry["val"] else None

    def save_best(self, entry: dict) -> None:
        weights.save(self.folder, "oidn_ft", self.net.state_dict(), {
            "network": self.o.network, "prior_sha256": self.prior_sha, "spp": self.spps,
            "widths": self.net.widths, "epoch": entry["epoch"], "metrics": entry["val"],
            "train_loss": entry["train_loss"], "store": str(self.cfg.store), "settings": self.fingerprint})

    def write_history(self, history: list, best: dict | None) -> None:
        atomic_write_json(self.folder / "train.json", {"network": self.o.network, "history": history, "best": best})
        curves = {"train loss": [(h["epoch"], h["train_loss"]) for h in history if h["train_loss"] is not None]}
        gain = {"val PSNR - stock OIDN (dB)": [(h["epoch"], h["val"]["psnr"] - h["val"]["oidn_psnr"])
                                              for h in history if h.get("val")]}
        plot_curves(self.folder / "loss.png", curves, f"oidn_ft ({self.o.network}) on {self.cfg.store}",
                    right=gain, right_label="dB")

    def when_done(self, history: list, best: dict | None) -> None:
        if history:
            self.write_history(history, best)

    def epoch_line(self, entry: dict) -> str:
        v, loss = entry["val"], entry["train_loss"]
        line = f"{self.name} epoch {entry['epoch']}: train loss " + ("n/a" if loss is None else f"{loss:.5f}")
        if entry["skipped_steps"]:
            line += f", {entry['skipped_steps']} non-finite steps skipped"
        if v:
            gains = " ".join(f"{k[8:]} {v[k]:+.3f}" for k in v if k.startswith("gain_spp"))
            line += f", val PSNR {v['psnr']:.3f} dB (stock OIDN {v['oidn_psnr']:.3f}; gain by spp: {gains})"
        return line

    def best_text(self, best: dict) -> str:
        v = best["val"]
        if not v:
            return f"best epoch {best['epoch']}"
        return f"best epoch {best['epoch']}: val PSNR {v['psnr']:.3f} dB, {v['psnr'] - v['oidn_psnr']:+.3f} dB over stock OIDN"


def train(cfg: Config, spp="any", quiet: bool = False) -> dict:
    """Train (or resume) ``oidn_ft`` and return ``clean.fit``'s summary."""
    if str(spp) != "any":
        raise TrainError("oidn_ft is one model for every sample count, as OIDN's own: use SPP=any")
    return fit(OIDNFineTune(cfg, spp), quiet=quiet)


# ---- using a run -------------------------------------------------------------------------------


def export_blob(net: UNet) -> bytes:
    """The float16 TZA blob OIDN runs (``train.oidn.denoise(weights=...)``, a host's ``weights``)."""
    return write_tza(net.to_tza())


def load_run(folder: Path, cfg: Config, blend: float | None = None) -> tuple[UNet, dict]:
    """The best weights of an oidn_ft run, blended with its prior (``blend``; default the config's
    ``oidn_ft.blend``), and its model.json with the blend used. The prior must be the one the run
    started from."""
    folder = Path(folder)
    record = weights.read_record(folder, "oidn_ft", "run `make train MODEL=oidn_ft SPP=any`")
    name = record["network"]
    blob = oidn.weights_blob(name, oidn.weights_source(name, cfg.oidn.weights))
    weights.check_sha256(blob, record["prior_sha256"], f"{folder}: the {name} prior "
                         f"({cfg.oidn.weights or 'pyoidn built-in'})", "set oidn.weights to the run's prior")
    base = UNet.from_tza(read_tza(blob, name))
    net = UNet(record["widths"])
    net.load_state_dict(weights.load_tensors(folder / "model.safetensors"))
    a = cfg.oidn_ft.blend if blend is None else float(blend)
    net.load_state_dict(blended(base.state_dict(), net.state_dict(), a))
    return net.eval(), {**record, "blend": a}


def blended(prior: dict, trained: dict, a: float) -> dict:
    """WiSE-FT: ``prior + a × (trained − prior)`` per tensor (torch or numpy); ``a`` 0 is the prior
    exactly (the formula would turn its −0.0 into +0.0), 1 the trained weights exactly."""
    if a == 0.0:
        return dict(prior)
    if a == 1.0:
        return dict(trained)
    return {k: prior[k] + a * (trained[k] - prior[k]) for k in trained}
