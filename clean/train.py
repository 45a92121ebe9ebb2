"""Training of the affinity network: the GT cleaner (GT1 ↔ GT2, paper eq. 1) or the Isik baseline
(low-spp buffers at ``spp`` → GT_clean).

    train(cfg, mode="cleaner")          → runs/<...>/cleaner/
    train(cfg, mode="baseline", spp=4)  → runs/<...>/isik_spp4/
    train(cfg, mode="baseline", spp="any") → runs/<...>/isik_sppany/ (trained at 4, 8, ... 64 spp)

Loss SMAPE (``clean.losses.smape``, ε = ``clean.smape_eps``), AdamW, random crops and flips from
the train split; after every epoch a validation pass over the whole frames of the val split
(SMAPE, L1 and PSNR). Files of a run folder:

- ``model.safetensors`` + ``model.json``: the best epoch so far (lowest validation SMAPE; the
  training loss where the val split is empty). What ``clean.apply`` and the evaluator load
  (``clean.model.load_model``).
- ``last.safetensors``: the state after the last finished epoch, one file written atomically:
  weights (``model.*``), AdamW moments (``optim.*``), the torch RNG state, and in the safetensors
  metadata a JSON record (epoch, history, best, optimizer hyper-parameters, config fingerprint).
  A rerun resumes from it and gives bitwise the weights of an uninterrupted run: each epoch's
  crops come from ``default_rng([seed, epoch, item])``, independent of what ran before.
- ``loss.png``: training and validation loss per epoch; ``train.json``: the history as JSON.

No pickle anywhere: everything is safetensors or JSON.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from pipeline.config import Config
from pipeline.progress import progress
from pipeline.checkpoint import load_last, plot_curves, save_last, save_safetensors
from pipeline.exr import StoreError, atomic_write_json
from pipeline.metrics import all_metrics
from pipeline.store import Store

from .data import COLOR_VARIANCE_CHANNEL, IN_CHANNELS, BaselinePairs, CleanerPairs, baseline_images, channel_names, usable_frames
from .losses import smape
from .model import AffinityDenoiser

FORMAT = "mcdenoise-affinity"
PSNR_CEILING = 999.0


class TrainError(StoreError):
    """The run cannot proceed (no data, incompatible checkpoint); the message says what to do.

    A ``StoreError``, so ``python -m pipeline`` prints it as one line and exits with status 2."""


def run_dir(cfg: Config, mode: str = "cleaner", spp: int | str | None = None) -> Path:
    if mode == "cleaner":
        return Path(cfg.runs) / "cleaner"
    if mode == "baseline":
        return Path(cfg.runs) / f"isik_spp{spp if str(spp) == 'any' else int(spp)}"
    raise ValueError(f"mode must be 'cleaner' or 'baseline', got {mode!r}")


def baseline_checkpoint(cfg: Config, spp: int) -> Path | None:
    """The Isik baseline that serves ``spp``: the run trained at that spp (isik_spp<N>) if there is
    one, else the spp-conditioned run (isik_sppany) when it was trained on that count; None if neither."""
    own = run_dir(cfg, "baseline", spp)
    if (own / "model.safetensors").exists():
        return own
    anyspp = run_dir(cfg, "baseline", "any")
    if (anyspp / "model.safetensors").exists() and int(spp) in trained_spps(anyspp):
        return anyspp
    return None


def trained_spps(folder: Path) -> list[int]:
    """Sample counts a baseline run trained on (its model.json; older runs name one spp)."""
    record = json.loads((folder / "model.json").read_text())
    return [int(s) for s in record.get("spp_choices") or [record["spp"]]]


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


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


# ---- data ------------------------------------------------------------------------------------


def datasets(cfg: Config, mode: str, spp: int | str | None):
    store = Store(cfg.store)
    c = cfg.clean
    spps = store.spp_choices(spp) if mode == "baseline" else None

    def keys(split: str) -> list:
        if split not in store.manifest()["splits"]:
            return []
        if mode == "cleaner":
            return usable_frames(store, split, ["gt1", "gt2"])
        return [k for k in usable_frames(store, split, ["gt1"])
                if all(store.image_path(k.scene, k.frame, n).exists() for n in baseline_images(store, k, max(spps)))]

    train_keys, val_keys = keys("train"), keys("val")
    if not train_keys:
        need = "gt1/gt2" if mode == "cleaner" else f"gt_clean and the stacks for {spp} spp (run make gt-clean)"
        raise TrainError(f"{store.root}: no complete training frame with {need}")
    make = ((lambda k, crop, n: CleanerPairs(store, k, crop, n, cfg.seed)) if mode == "cleaner" else
            (lambda k, crop, n: BaselinePairs(store, k, spps, crop, n, cfg.seed)))
    train_ds = make(train_keys, c.crop, c.crops_per_frame)
    val_ds = make(val_keys, None, 1) if val_keys else None
    return train_ds, val_ds


# ---- checkpoints -----------------------------------------------------------------------------


def save_best(folder: Path, model: AffinityDenoiser, record: dict) -> None:
    save_safetensors(folder / "model.safetensors", model.state_dict(), {"format": FORMAT})
    atomic_write_json(folder / "model.json", record)


def plot_curve(path: Path, history: list[dict], title: str) -> None:
    """Training and validation SMAPE per epoch (log scale) as a PNG, written atomically."""
    val = [(h["epoch"], h["val"]["smape"]) for h in history if h.get("val")]
    curves = {"train SMAPE": [(h["epoch"], h["train_loss"]) for h in history]}
    if val:
        curves["val SMAPE"] = val
    plot_curves(path, curves, title, xlabel="epoch", ylabel="loss")


# ---- loops -----------------------------------------------------------------------------------


@torch.no_grad()
def validate(model: AffinityDenoiser, ds, cfg: Config, device) -> dict[str, float]:
    """Mean SMAPE / L1 (HDR, clamped to [0, 6]) / PSNR (x/(1+x), peak 1) over whole frames."""
    from .apply import denoise

    model.eval()
    rows = []
    for i in range(len(ds)):
        item = ds[i]
        out = denoise(model, item["inputs"].numpy(), item["radiance"].numpy(), tile=cfg.clean.tile, device=device)
        row = all_metrics(out, np.moveaxis(item["target"].numpy(), 0, 2), eps=cfg.clean.smape_eps)
        # Identical images have PSNR inf, which JSON cannot hold: record a ceiling instead.
        rows.append({**row, "psnr": min(row["psnr"], PSNR_CEILING)})
    model.train()
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def train(cfg: Config, mode: str = "cleaner", spp: int | None = None, quiet: bool = False) -> dict:
    """Train (or resume) and return a summary dict; the best weights end up in ``run_dir``."""
    t_start = time.perf_counter()
    if mode == "baseline" and not spp:
        raise TrainError("the Isik baseline needs an spp (make train MODEL=isik SPP=4)")
    c = cfg.clean
    folder = run_dir(cfg, mode, spp)
    device = pick_device(c.device)
    torch.manual_seed(cfg.seed)
    model = build_model(cfg).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=c.lr, weight_decay=c.weight_decay)
    fp = fingerprint(cfg, mode, spp)
    history: list[dict] = []
    best: dict | None = None
    start = 0
    last = folder / "last.safetensors"
    # Temporary files of a write a kill interrupted (one trainer per run folder: all stale).
    for tmp in folder.glob(".*.tmp") if folder.is_dir() else ():
        tmp.unlink(missing_ok=True)
    if last.exists():
        record = load_last(last, model, opt, device, fingerprint=fp)
        start, history, best = int(record["epoch"]), record["history"], record["best"]
    title = "GT cleaner (GT1 <-> GT2)" if mode == "cleaner" else f"Isik baseline, {spp} spp -> GT_clean"
    if start >= c.epochs:
        if history:
            _write_history(folder, mode, spp, history, best, title, only_if_changed=True)
        summary = _summary(folder, mode, spp, history, best, 0, time.perf_counter() - t_start)
        if not quiet:
            print(f"{folder.name}: already trained ({start} epochs); {summary['line']}")
        return summary

    train_ds, val_ds = datasets(cfg, mode, spp)
    spps = getattr(train_ds, "spps", None)
    trained = 0
    for epoch in range(start, c.epochs):
        train_ds.set_epoch(epoch)
        order = np.random.default_rng([cfg.seed, epoch]).permutation(len(train_ds)).tolist()
        loader = DataLoader(train_ds, batch_size=c.batch_size, sampler=order, num_workers=0)
        model.train()
        losses = []
        bar = progress(loader, desc=f"{folder.name} epoch {epoch + 1}/{c.epochs}", unit="step", disable=quiet,
                       leave=False)
        for batch in bar:
            inputs, radiance, target = (batch[k].to(device) for k in ("inputs", "radiance", "target"))
            loss = smape(model(inputs, radiance), target, c.smape_eps)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if c.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), c.grad_clip)
            opt.step()
            losses.append(float(loss.detach()))
            bar.set_postfix(smape=f"{np.mean(losses):.4f}")
        entry = {"epoch": epoch + 1, "train_loss": float(np.mean(losses)),
                 "val": validate(model, val_ds, cfg, device) if val_ds is not None else None,
                 "seconds": time.perf_counter() - t_start}
        history.append(entry)
        trained += 1
        score = entry["val"]["smape"] if entry["val"] else entry["train_loss"]
        if best is None or score < best["score"]:
            best = {"epoch": epoch + 1, "score": score, "val": entry["val"], "train_loss": entry["train_loss"]}
            save_best(folder, model, {"format": FORMAT, "mode": mode, "spp": spp, "spp_choices": spps,
                                      "hparams": model.hparams,
                                      "input_channels": channel_names(), "epoch": epoch + 1,
                                      "metrics": entry["val"], "train_loss": entry["train_loss"],
                                      "smape_eps": c.smape_eps, "store": str(cfg.store), "clean": vars(c).copy()})
        # last.safetensors is the commit point of an epoch, so it is written last: a kill before it
        # reruns the epoch (same result) and rewrites the files above.
        _write_history(folder, mode, spp, history, best, title)
        save_last(last, model, opt, {"epoch": epoch + 1, "history": history, "best": best, "fingerprint": fp},
                  FORMAT)
        if not quiet:
            val = entry["val"]
            print(f"{folder.name} epoch {epoch + 1}: train SMAPE {entry['train_loss']:.4f}"
                  + (f", val SMAPE {val['smape']:.4f} L1 {val['l1']:.4f} PSNR {val['psnr']:.2f} dB" if val else ""),
                  flush=True)
        if c.time_budget_s > 0 and time.perf_counter() - t_start >= c.time_budget_s and epoch + 1 < c.epochs:
            if not quiet:
                print(f"{folder.name}: time budget of {c.time_budget_s:g} s reached after epoch {epoch + 1}; "
                      f"rerun to resume")
            break
    summary = _summary(folder, mode, spp, history, best, trained, time.perf_counter() - t_start)
    if not quiet:
        print(summary["line"], flush=True)
    return summary


def _write_history(folder: Path, mode: str, spp, history: list, best, title: str,
                   only_if_changed: bool = False) -> None:
    """train.json and loss.png from the history (repaired if a kill left them an epoch behind)."""
    record = {"mode": mode, "spp": spp, "history": history, "best": best}
    path = folder / "train.json"
    if only_if_changed and path.exists():
        try:
            if json.loads(path.read_text()) == record:
                return
        except (OSError, ValueError):
            pass
    plot_curve(folder / "loss.png", history, title)
    atomic_write_json(path, record)


def _summary(folder: Path, mode: str, spp, history: list, best: dict | None, trained: int, seconds: float) -> dict:
    epochs = history[-1]["epoch"] if history else 0
    line = f"{folder.name}: {epochs} epochs ({trained} this run, {seconds:.1f} s)"
    if best:
        v = best["val"]
        line += (f"; best epoch {best['epoch']}: " + (f"val SMAPE {v['smape']:.4f}, L1 {v['l1']:.4f}, "
                                                      f"PSNR {v['psnr']:.2f} dB" if v else
                                                      f"train SMAPE {best['train_loss']:.4f}"))
    line += f" -> {folder / 'model.safetensors'}"
    return {"mode": mode, "spp": spp, "folder": str(folder), "epochs": epochs, "trained_epochs": trained,
            "best": best, "seconds": seconds, "line": line}
