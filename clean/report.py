"""``python -m pipeline clean-report``: is GT_clean closer to an independent GT2 than GT1 is?

GT1 and GT2 are independent estimates of the same image, so against GT2 a perfect cleaner halves
the mean squared error of GT1 (GT2's own noise stays in both). The report measures, on the
val (and test) frames, PSNR on the x/(1+x) tonemap, L1 in HDR clamped to [0, 6] and SMAPE of
GT1 vs GT2 and of GT_clean vs GT2, and draws a crop grid GT1 / GT_clean / GT2 (gamma tonemap, as
the paper's figures) so a reader can check that no detail was blurred away. With ``--spp N`` it
also scores the Isik baseline trained at N spp on the test split against GT_clean, next to the
noisy input.

Writes ``<out>/cleaner.md``, ``<out>/cleaner.json`` and ``<out>/cleaner_crops.png``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mcdenoise.pipeline import figures
from mcdenoise.pipeline.config import Config, pick_device
from mcdenoise.pipeline.exr import StoreError
from mcdenoise.pipeline.metrics import all_metrics, mse, reinhard
from mcdenoise.pipeline.store import Store

from .data import frame_inputs
from .model import load_model
from .train import baseline_checkpoint, run_dir, wall_seconds


def _mean_rows(rows: list[dict]) -> dict:
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]} if rows else {}


def cleaner_metrics(store: Store, split: str, eps: float, untrained=None, tile: int = 512, device="cpu") -> dict:
    """GT1 and GT_clean against GT2 over ``split``; with ``untrained`` (a fresh model, see
    ``untrained_model``) also that network's output from GT1, in the same pass over the frames."""
    from .apply import denoise

    rows_gt1, rows_clean, rows_untrained, mse_ratio, tm_ratio = [], [], [], [], []
    for key in store.frames_with(split):
        gt1 = store.read_image(key.scene, key.frame, "gt1", None if untrained else ["color"])[0]
        g1 = gt1["color"]
        g2 = store.read_image(key.scene, key.frame, "gt2", ["color"])[0]["color"]
        gc = store.read_image(key.scene, key.frame, "gt_clean", ["color"])[0]["color"]
        rows_gt1.append(all_metrics(g1, g2, eps))
        rows_clean.append(all_metrics(gc, g2, eps))
        if untrained is not None:
            rows_untrained.append(all_metrics(denoise(untrained, *frame_inputs(gt1), tile=tile, device=device), g2, eps))
        mse_ratio.append(mse(gc, g2) / max(mse(g1, g2), 1e-30))
        tm_ratio.append(mse(reinhard(gc), reinhard(g2)) / max(mse(reinhard(g1), reinhard(g2)), 1e-30))
    return {"frames": len(rows_gt1), "gt1_vs_gt2": _mean_rows(rows_gt1), "clean_vs_gt2": _mean_rows(rows_clean),
            "untrained_vs_gt2": _mean_rows(rows_untrained) or None,
            "mse_ratio_mean": float(np.mean(mse_ratio)) if mse_ratio else None,
            "mse_ratio_tonemapped_mean": float(np.mean(tm_ratio)) if tm_ratio else None}


def untrained_model(cfg: Config):
    """The cleaner's network as training starts it (same seed), or None without the range term:
    scoring it shows how much of the gain is the range term's fixed NL-means prior and how much
    is learned."""
    import torch

    from .train import build_model

    if not cfg.clean.range_term:
        return None
    torch.manual_seed(cfg.seed)
    return build_model(cfg).to(pick_device(cfg.clean.device))


def baseline_metrics(cfg: Config, store: Store, spp: int, split: str = "test") -> dict:
    from .apply import denoise

    folder = baseline_checkpoint(cfg, spp)
    if folder is None:
        raise StoreError(f"no Isik baseline for {spp} spp in {run_dir(cfg, 'baseline', spp)} or "
                         f"{run_dir(cfg, 'baseline', 'any')}: run `make train MODEL=isik SPP={spp}` (or SPP=any)")
    model, _ = load_model(folder)
    device = pick_device(cfg.clean.device)
    rows_noisy, rows_den = [], []
    for key in store.frames_with(split):
        buffers = store.read(key.scene, key.frame, spp)
        target = store.read_image(key.scene, key.frame, "gt_clean", ["color"])[0]["color"]
        inputs, radiance = frame_inputs(buffers)
        out = denoise(model, inputs, radiance, tile=cfg.clean.tile, device=device)
        rows_noisy.append(all_metrics(buffers["color"], target, cfg.clean.smape_eps))
        rows_den.append(all_metrics(out, target, cfg.clean.smape_eps))
    return {"spp": spp, "checkpoint": folder.name, "split": split, "frames": len(rows_den),
            "noisy": _mean_rows(rows_noisy),
            "isik": _mean_rows(rows_den)}


# Gain of the difference columns of the crop grid: 1024-spp noise is ~0.005 on the x/(1+x) scale,
# invisible next to the image itself.
DIFF_GAIN = 20.0


def crop_grid(store: Store, split: str, path: Path, rows: int = 4, size: int = 64) -> None:
    """GT1 / GT_clean / GT2 crops, then ×DIFF_GAIN absolute differences on the x/(1+x) scale:
    GT1−GT2 (noise of both), GT_clean−GT2 (what is left), GT_clean−GT1 (what the cleaner
    removed: it should look like noise, and any edge or texture in it is detail blurred away)."""
    def diff(a, b):
        return DIFF_GAIN * np.abs(reinhard(a) - reinhard(b))

    keys = store.frames_with(split)[:rows]
    grid = []
    for key in keys:
        g1, gc, g2 = (store.read_image(key.scene, key.frame, n, ["color"])[0]["color"]
                      for n in ("gt1", "gt_clean", "gt2"))
        grid.append((str(key), [g1, gc, g2, diff(g1, g2), diff(gc, g2), diff(gc, g1)]))
    g = f"×{DIFF_GAIN:g}"
    figures.crop_grid(grid, ["GT1", "GT_clean", "GT2", f"|GT1−GT2| {g}", f"|GT_clean−GT2| {g}",
                             f"|GT_clean−GT1| {g} (removed)"], path, size=size, reference=2)


def run_report(cfg: Config, out: str = "reports/cleaner", spp: int | None = None) -> dict:
    store = Store(cfg.store)
    eps = cfg.clean.smape_eps
    untrained = untrained_model(cfg)
    result = {"store": str(cfg.store), "smape_eps": eps,
              **{split: cleaner_metrics(store, split, eps, untrained, cfg.clean.tile, pick_device(cfg.clean.device))
                 for split in ("val", "test")}}
    train_json = run_dir(cfg, "cleaner") / "train.json"
    if train_json.exists():
        hist = json.loads(train_json.read_text())
        # the curve is loss.png beside it; seconds over every invocation of a resumed run
        result["training"] = {"epochs": len(hist["history"]), "best_epoch": hist["best"]["epoch"],
                              "seconds": wall_seconds(hist["history"]),
                              "val_smape_per_epoch": [h["val"]["smape"] for h in hist["history"] if h.get("val")]}
    if spp is not None:
        result["baseline"] = baseline_metrics(cfg, store, spp)
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    crop_grid(store, "val", out_dir / "cleaner_crops.png")
    (out_dir / "cleaner.json").write_text(json.dumps(result, indent=1) + "\n")
    md = format_markdown(result)
    (out_dir / "cleaner.md").write_text(md)
    print(md)
    return result


def format_markdown(r: dict) -> str:
    def row(name, m):
        return f"| {name} | {m['psnr']:.2f} | {m['l1']:.5f} | {m['smape']:.4f} |"

    lines = [f"# GT cleaner (store {r['store']}, SMAPE eps {r['smape_eps']})", ""]
    if "training" in r:
        t = r["training"]
        lines += [f"Training: {t['epochs']} epochs in {t['seconds']:.0f} s, best epoch {t['best_epoch']} "
                  "(curve: loss.png in the cleaner's run folder).", ""]
    for split in ("val", "test"):
        s = r[split]
        if not s["frames"]:
            continue
        lines += [f"## {split} split: {s['frames']} frames, against an independent GT2", "",
                  "| image | PSNR dB (x/(1+x)) | L1 (HDR, [0,6]) | SMAPE |", "| --- | --- | --- | --- |",
                  row("GT1", s["gt1_vs_gt2"]), row("GT_clean", s["clean_vs_gt2"])]
        if s.get("untrained_vs_gt2"):
            lines.append(row("untrained network, range term only", s["untrained_vs_gt2"]))
        lines += ["",
                  f"MSE(GT_clean, GT2) / MSE(GT1, GT2), mean over frames: {s['mse_ratio_mean']:.3f} in HDR, "
                  f"{s['mse_ratio_tonemapped_mean']:.3f} on the x/(1+x) scale of the PSNR "
                  "(1 = no gain; 0.5 = a perfect cleaner)", ""]
    if "baseline" in r and not r["baseline"]["frames"]:
        b = r["baseline"]
        lines += [f"## Isik baseline at {b['spp']} spp: no {b['split']} frame with gt_clean to score", ""]
    elif "baseline" in r:
        b = r["baseline"]
        lines += [f"## Isik baseline at {b['spp']} spp, {b['split']} split ({b['frames']} frames), against GT_clean", "",
                  "| method | PSNR dB | L1 | SMAPE |", "| --- | --- | --- | --- |",
                  row("noisy input", b["noisy"]), row(f"Isik ({b.get('checkpoint', '')})", b["isik"]), ""]
    lines.append("Crops (gamma tonemap): cleaner_crops.png")
    return "\n".join(lines) + "\n"
