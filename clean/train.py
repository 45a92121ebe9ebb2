"""Training of the networks on ``clean.data``'s inputs, one loop for every recipe: the GT cleaner
(GT1 ↔ GT2, paper eq. 1) and the Isik baseline (low-spp buffers at ``spp`` → GT_clean).

    train(cfg, mode="cleaner")          → runs/<...>/cleaner/
    train(cfg, mode="baseline", spp=4)  → runs/<...>/isik_spp4/
    train(cfg, mode="baseline", spp="any") → runs/<...>/isik_sppany/ (trained at 4, 8, ... 64 spp)

A ``Recipe`` holds what differs between trainers: the networks, their optimizers, one optimisation
step, the config section with the loop's settings, the run folder and the training target. The
cleaner and the Isik baseline: SMAPE (``clean.losses.smape``, ε = ``clean.smape_eps``), AdamW.
``train_recipe`` trains any recipe, so a network of another package on the same inputs (a
competitor baseline) brings its own recipe and reuses the loop.

``train_recipe`` runs a recipe through the loop every trainer shares (``clean.fit``; ``RecipeTask``
says what is particular here): random crops and flips from the train split; a NaN guard (a step
whose loss or gradient norm is not finite is skipped and counted, ``nan_limit`` in a row within
an epoch stop the run with an error); after every epoch a validation pass over the whole frames
of the val split (SMAPE, L1 and PSNR). Files of a run folder:

- ``model.safetensors`` + ``model.json``: the best epoch so far (lowest validation SMAPE; the
  training loss where the val split is empty). What ``clean.apply`` and the evaluator load
  (``clean.model.load_model``).
- ``last.safetensors``: the state after the last finished epoch, one file written atomically:
  weights (``model.*``; every module of the recipe's ``state``), optimizer moments (``optim.*``), the torch
  RNG state, and in the safetensors metadata a JSON record (epoch, history, best, optimizer
  hyper-parameters, config fingerprint). A rerun resumes from it and gives bitwise the weights of
  an uninterrupted run: each epoch's crops come from ``default_rng([seed, epoch, item])`` and each
  step's other random draws from a generator seeded by (seed, epoch, step), independent of what
  ran before.
- ``loss.png``: training and validation loss per epoch; ``train.json``: the history as JSON.

No pickle anywhere: everything is safetensors or JSON.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch.utils.data import DataLoader

from mcdenoise.pipeline import config as config_mod, weights
from mcdenoise.pipeline.config import Config, pick_device
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.exr import atomic_write_json
from mcdenoise.pipeline.figures import plot_curves
from mcdenoise.pipeline.metrics import PSNR_CEILING, all_metrics
from mcdenoise.pipeline.store import Store

from .data import (
    COLOR_VARIANCE_CHANNEL,
    IN_CHANNELS,
    BaselinePairs,
    CleanerPairs,
    baseline_images,
    channel_names,
    usable_frames,
)
from .fit import Task, apply_update, fit
from .losses import smape
from .model import AffinityDenoiser


def run_dir(cfg: Config, mode: str = "cleaner", spp: int | str | None = None) -> Path:
    """``pipeline.config.run_dir`` by this module's mode names (``baseline``: the Isik baseline)."""
    _check_mode(mode)
    return config_mod.run_dir(cfg, "isik" if mode == "baseline" else mode, spp)


def _check_mode(mode: str) -> None:
    if mode not in ("cleaner", "baseline"):
        raise ValueError(f"mode must be 'cleaner' or 'baseline', got {mode!r}")


def baseline_checkpoint(cfg: Config, spp: int) -> Path | None:
    """The Isik baseline that serves ``spp``: the run trained at that spp (isik_spp<N>) if there is
    one, else the spp-conditioned run (isik_sppany) when it was trained on that count; None if neither."""
    return config_mod.find_run(cfg, "isik", spp, "model.safetensors", serves=lambda folder: int(spp) in trained_spps(folder))


def trained_spps(folder: Path) -> list[int]:
    """Sample counts a baseline run trained on: its model.json's ``spp_choices``, or the one ``spp`` of a
    record without them."""
    record = json.loads((folder / "model.json").read_text())
    return [int(s) for s in record.get("spp_choices") or [record["spp"]]]


def build_model(cfg: Config) -> AffinityDenoiser:
    return AffinityDenoiser(**build_model_hparams(cfg))


def fingerprint(cfg: Config, mode: str, spp: int | None) -> dict:
    """What must not change between a checkpoint and the run resuming it (epochs, time budget
    and device may)."""
    c = cfg.clean
    return {"mode": mode, "spp": spp, "seed": cfg.seed, "hparams": build_model_hparams(cfg),
            **{k: getattr(c, k) for k in ("batch_size", "crop", "crops_per_frame", "lr", "weight_decay",
                                          "smape_eps", "grad_clip")}}


def build_model_hparams(cfg: Config) -> dict:
    c = cfg.clean
    return {"in_channels": IN_CHANNELS, "embed_channels": c.embed_channels, "channels": list(c.channels),
            "affinity_channels": c.affinity_channels, "kernel_size": c.kernel_size, "dilations": list(c.dilations),
            "variance_channel": COLOR_VARIANCE_CHANNEL if c.range_term else None, "range_patch": c.range_patch}


# ---- recipes ---------------------------------------------------------------------------------


@dataclass
class Recipe:
    """What one trainer optimises; ``train_recipe`` runs any of them."""
    mode: str
    spp: object                   # int, "any" or None (the cleaner)
    settings: object              # a config section (cfg.clean, ...): epochs, batch_size, crop,
    #                               crops_per_frame, grad_clip, nan_limit, time_budget_s, tile, device
    model: torch.nn.Module        # validated, saved as model.safetensors
    state: torch.nn.Module        # saved in last.safetensors (the model, or the model and its critic)
    optimizers: object            # an optimizer, or a dict name -> optimizer
    step: Callable                # (batch on the device, torch.Generator) -> ({"loss": ..., terms}, finite)
    fingerprint: dict
    kind: str                     # its kind of weight file (pipeline.weights.FORMATS)
    title: str
    loss_label: str
    folder: Path                  # the run folder
    target: str = "gt_clean"
    meta: dict = field(default_factory=dict)


def affinity_recipe(cfg: Config, mode: str, spp: int | None, device) -> Recipe:
    """The cleaner (mode 'cleaner') or the Isik baseline ('baseline'): SMAPE, AdamW."""
    c = cfg.clean
    torch.manual_seed(cfg.seed)
    model = build_model(cfg).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=c.lr, weight_decay=c.weight_decay)
    params = list(model.parameters())

    def step(batch: dict, generator: torch.Generator) -> tuple[dict, bool]:
        loss = smape(model(batch["inputs"], batch["radiance"]), batch["target"], c.smape_eps)
        return {"loss": float(loss.detach())}, apply_update(loss, opt, params, c.grad_clip)

    title = "GT cleaner (GT1 <-> GT2)" if mode == "cleaner" else f"Isik baseline, {spp} spp -> GT_clean"
    return Recipe(mode, spp, c, model, model, opt, step, fingerprint(cfg, mode, spp), "affinity", title, "SMAPE",
                  run_dir(cfg, mode, spp), meta={"smape_eps": c.smape_eps, "clean": vars(c).copy()})


def make_recipe(cfg: Config, mode: str, spp) -> Recipe:
    if mode == "baseline" and not spp:
        raise TrainError("the isik model needs an spp (make train MODEL=isik SPP=4)")
    _check_mode(mode)
    return affinity_recipe(cfg, mode, spp, pick_device(cfg.clean.device))


# ---- data ------------------------------------------------------------------------------------


def datasets(cfg: Config, recipe: Recipe):
    store = Store(cfg.store)
    s, mode = recipe.settings, recipe.mode
    spps = store.spp_choices(recipe.spp) if mode != "cleaner" else []

    def keys(split: str) -> list:
        if mode == "cleaner":
            return usable_frames(store, split, ["gt1", "gt2"])
        return [k for k in usable_frames(store, split, ["gt1"])
                if all(store.image_path(k.scene, k.frame, n).exists()
                       for n in baseline_images(store, k, max(spps), recipe.target))]

    train_keys, val_keys = keys("train"), keys("val")
    if not train_keys:
        need = ("gt1/gt2" if mode == "cleaner" else
                f"{recipe.target} and the stacks for {max(spps)} spp" + (" (run make gt-clean)"
                                                                         if recipe.target == "gt_clean" else ""))
        raise TrainError(f"{store.root}: no complete training frame with {need}")
    make = ((lambda k, crop, n: CleanerPairs(store, k, crop, n, cfg.seed)) if mode == "cleaner" else
            (lambda k, crop, n: BaselinePairs(store, k, spps if len(spps) > 1 else spps[0], crop, n, cfg.seed,
                                              recipe.target)))
    train_ds = make(train_keys, s.crop, s.crops_per_frame)
    val_ds = make(val_keys, None, 1) if val_keys else None
    return train_ds, val_ds


# ---- checkpoints -----------------------------------------------------------------------------


def save_best(folder: Path, model: torch.nn.Module, record: dict, kind: str = "affinity") -> None:
    weights.save(folder, kind, model.state_dict(), record)


def plot_curve(path: Path, history: list[dict], title: str, loss_label: str = "SMAPE") -> None:
    """Training loss and validation SMAPE per epoch as a PNG (log scale), written atomically; the
    critic's Wasserstein estimate, where there is one, on the right axis."""
    curves = {f"train {loss_label}": [(h["epoch"], h["train_loss"]) for h in history if h["train_loss"] is not None]}
    val = [(h["epoch"], h["val"]["smape"]) for h in history if h.get("val")]
    if val:
        curves["val SMAPE"] = val
    critic = [(h["epoch"], h["terms"]["wasserstein"]) for h in history if "wasserstein" in h.get("terms", {})]
    right = {"critic: E[D(target)] - E[D(output)]": critic} if critic else None
    plot_curves(path, curves, title, xlabel="epoch", ylabel="loss", right=right, right_label="critic")


# ---- loops -----------------------------------------------------------------------------------


@torch.no_grad()
def validate(model: torch.nn.Module, ds, tile: int, eps: float, device) -> dict[str, float]:
    """Mean SMAPE / L1 (HDR, clamped to [0, 6]) / PSNR (x/(1+x), peak 1) over whole frames."""
    from .apply import denoise

    model.eval()
    rows = []
    for i in range(len(ds)):
        item = ds[i]
        out = denoise(model, item["inputs"].numpy(), item["radiance"].numpy(), tile=tile, device=device)
        row = all_metrics(out, np.moveaxis(item["target"].numpy(), 0, 2), eps=eps)
        # Identical images have PSNR inf, which JSON cannot hold: record a ceiling instead.
        rows.append({**row, "psnr": min(row["psnr"], PSNR_CEILING)})
    model.train()
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def _step_generator(seed: int, epoch: int, step: int) -> torch.Generator:
    """The random draws of one step (e.g. a gradient penalty's mix), a pure function of its position."""
    return torch.Generator().manual_seed(int(np.random.default_rng([seed, epoch, step]).integers(2 ** 62)))


class RecipeTask(Task):
    """A ``Recipe`` as ``clean.fit`` trains it: crops of the train split, whole val frames, the best
    by validation SMAPE (the training loss where the val split is empty)."""

    minimize = True

    def __init__(self, cfg: Config, recipe: Recipe):
        s = recipe.settings
        self.cfg, self.recipe, self.folder = cfg, recipe, recipe.folder
        self.name, self.epochs, self.time_budget_s, self.nan_limit = self.folder.name, s.epochs, s.time_budget_s, s.nan_limit
        self.fingerprint, self.state, self.optimizers = recipe.fingerprint, recipe.state, recipe.optimizers
        self.fmt = weights.FORMATS[recipe.kind]
        self.device = pick_device(s.device)
        self.output = str(self.folder / "model.safetensors")
        self.train_ds = self.val_ds = None

    def when_done(self, history: list, best: dict | None) -> None:
        if history:
            _write_history(self.folder, self.recipe, history, best, only_if_changed=True)

    def prepare(self) -> None:
        self.train_ds, self.val_ds = datasets(self.cfg, self.recipe)

    def batches(self, epoch: int):
        self.train_ds.set_epoch(epoch)
        order = np.random.default_rng([self.cfg.seed, epoch]).permutation(len(self.train_ds)).tolist()
        self.recipe.state.train()
        return DataLoader(self.train_ds, batch_size=self.recipe.settings.batch_size, sampler=order, num_workers=0)

    def step(self, batch: dict, epoch: int, index: int) -> tuple[dict, bool]:
        return self.recipe.step(batch, _step_generator(self.cfg.seed, epoch, index))

    def entry(self, epoch: int, kept: list[dict], skipped: int) -> dict:
        entry = {"epoch": epoch + 1, "train_loss": float(np.mean([t["loss"] for t in kept])) if kept else None}
        extra = sorted({k for t in kept for k in t} - {"loss"})
        if extra:
            entry["terms"] = {k: float(np.mean([t[k] for t in kept])) for k in extra}
        entry["skipped_steps"] = skipped
        return entry

    def validate(self) -> dict | None:
        if self.val_ds is None:
            return None
        return validate(self.recipe.model, self.val_ds, self.recipe.settings.tile, self.cfg.clean.smape_eps,
                        self.device)

    def score(self, entry: dict) -> float | None:
        return entry["val"]["smape"] if entry["val"] else entry["train_loss"]

    def save_best(self, entry: dict) -> None:
        r, cfg = self.recipe, self.cfg
        save_best(self.folder, r.model, {"mode": r.mode, "spp": r.spp,
                                         "spp_choices": getattr(self.train_ds, "spps", None),
                                         "hparams": r.model.hparams, "input_channels": channel_names(),
                                         "epoch": entry["epoch"], "metrics": entry["val"],
                                         "train_loss": entry["train_loss"], "store": str(cfg.store), **r.meta}, r.kind)

    def write_history(self, history: list, best: dict | None) -> None:
        _write_history(self.folder, self.recipe, history, best)

    def epoch_line(self, entry: dict) -> str:
        val, loss = entry["val"], entry["train_loss"]
        line = f"{self.name} epoch {entry['epoch']}: train {self.recipe.loss_label} " + (
            "n/a" if loss is None else f"{loss:.4f}")
        line += "".join(f", {k} {v:.4g}" for k, v in entry.get("terms", {}).items())
        if entry["skipped_steps"]:
            line += f", {entry['skipped_steps']} non-finite steps skipped"
        if val:
            line += f", val SMAPE {val['smape']:.4f} L1 {val['l1']:.4f} PSNR {val['psnr']:.2f} dB"
        return line

    def best_text(self, best: dict) -> str:
        v = best["val"]
        return f"best epoch {best['epoch']}: " + (f"val SMAPE {v['smape']:.4f}, L1 {v['l1']:.4f}, "
                                                  f"PSNR {v['psnr']:.2f} dB" if v else
                                                  f"train loss {best['train_loss']:.4f}")

    def summary_fields(self) -> dict:
        return {"mode": self.recipe.mode, "spp": self.recipe.spp}


def train(cfg: Config, mode: str = "cleaner", spp: int | str | None = None, quiet: bool = False) -> dict:
    """Train (or resume) the cleaner or the Isik baseline and return a summary dict; the best weights
    end up in ``run_dir``."""
    return train_recipe(cfg, make_recipe(cfg, mode, spp), quiet=quiet)


def train_recipe(cfg: Config, recipe: Recipe, quiet: bool = False) -> dict:
    """Train (or resume) ``recipe`` through the shared loop and return a summary dict; the best weights
    end up in ``recipe.folder``."""
    return fit(RecipeTask(cfg, recipe), quiet=quiet)


def _write_history(folder: Path, recipe: Recipe, history: list, best, only_if_changed: bool = False) -> None:
    """train.json and loss.png from the history (repaired if a kill left them an epoch behind)."""
    record = {"mode": recipe.mode, "spp": recipe.spp, "history": history, "best": best}
    path = folder / "train.json"
    if only_if_changed and path.exists():
        try:
            if json.loads(path.read_text()) == record:
                return
        except (OSError, ValueError):
            pass
    plot_curve(folder / "loss.png", history, recipe.title, recipe.loss_label)
    atomic_write_json(path, record)


def wall_seconds(history: list[dict]) -> float:
    """Training wall time over every invocation: an entry's ``seconds`` count from the start of the
    invocation that trained it, so a resumed run starts counting again (a drop) and each
    invocation contributes its last value."""
    secs = [float(h["seconds"]) for h in history]
    return sum(t for t, nxt in zip(secs, secs[1:] + [0.0]) if nxt < t)


def gt_clean(cfg: Config, quiet: bool = False) -> int:
    """``gt-clean``: train the cleaner if needed (or resume it), then write GT_clean for every frame (frames made
    by the current checkpoint are skipped, so a rerun is cheap); the exit status (1: no frame to clean)."""
    from .apply import apply_cleaner

    train(cfg, mode="cleaner", quiet=quiet)
    stats = apply_cleaner(cfg, quiet=quiet)
    return 0 if stats["written"] + stats["skipped"] > 0 else 1
