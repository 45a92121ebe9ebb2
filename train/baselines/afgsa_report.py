"""``python -m pipeline afgsa-report --spp 4``: does AFGSA's adversarial loss learn the reference's noise?

The paper cleans its ground truth (its section 3.1) because a discriminator learns whatever noise
the target still has. This report compares AFGSA trained against GT_clean (``afgsa_spp<N>``) with
the same network, seed and crops trained against the raw GT1 (``afgsa.target=gt1``:
``afgsa_gt1_spp<N>``), both scored against GT_clean on ``eval.split``:

- PSNR (x/(1+x)), L1 (HDR, clamped to [0, 6]) and SMAPE against GT_clean;
- ``fine_energy`` ratio: the pixel-scale energy of an image over GT_clean's. Above 1 the image has
  more pixel-to-pixel variation than GT_clean (noise-like texture), below 1 it is smoother. GT1's
  own ratio says how much noise there was to learn;
- PSNR against the first run's output: how far apart the runs are. Another seed of the same target
  (``--run``) shows how far apart training alone puts two runs;
- the noisy input and GT1 itself as reference rows.

``--run LABEL=FOLDER`` adds any other AFGSA run (e.g. the L1-only ablation, ``afgsa.adv_weight=0``,
or another ``seed``, in another runs folder). Writes ``<out>/afgsa_targets.md``, ``.json`` and ``afgsa_targets_crops.png``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mcdenoise.clean.apply import denoise
from mcdenoise.clean.data import frame_inputs
from mcdenoise.clean.train import wall_seconds
from mcdenoise.pipeline import figures
from mcdenoise.pipeline.config import Config, pick_device, run_dir
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.metrics import all_metrics, reinhard
from mcdenoise.pipeline.store import Store

from .afgsa import load_model

DIFF_GAIN = 20.0          # the two outputs differ by ~1e-3 on the x/(1+x) scale: invisible unscaled


def fine_energy(img: np.ndarray) -> float:
    """Mean squared difference between the x/(1+x) image (H, W, 3) and its 3×3 box blur (edges
    replicated): the energy at the pixel scale, where Monte Carlo noise lives."""
    t = reinhard(np.maximum(np.asarray(img, np.float64), 0.0))
    p = np.pad(t, ((1, 1), (1, 1), (0, 0)), mode="edge")
    H, W = t.shape[:2]
    blur = sum(p[dy:dy + H, dx:dx + W] for dy in range(3) for dx in range(3)) / 9.0
    return float(np.mean((t - blur) ** 2))


def default_runs(cfg: Config, spp: int) -> dict[str, Path]:
    import dataclasses
    gt1 = dataclasses.replace(cfg, afgsa=dataclasses.replace(cfg.afgsa, target="gt1"))
    clean = dataclasses.replace(cfg, afgsa=dataclasses.replace(cfg.afgsa, target="gt_clean"))
    return {"AFGSA -> GT_clean": run_dir(clean, "afgsa", spp), "AFGSA -> GT1": run_dir(gt1, "afgsa", spp)}


def _score(images: dict[str, np.ndarray], ref: np.ndarray, eps: float, first: np.ndarray) -> dict[str, dict]:
    """Metrics against ``ref`` and the fine-energy ratio of every image; ``psnr_vs_first``: PSNR against
    the first run's output, how far apart two runs are (compare it with two seeds of one target)."""
    ref_energy = max(fine_energy(ref), 1e-30)
    return {name: {**all_metrics(img, ref, eps), "fine_energy_ratio": fine_energy(img) / ref_energy,
                   "psnr_vs_first": min(all_metrics(img, first, eps)["psnr"], 999.0)}
            for name, img in images.items()}


def _mean(rows: list[dict]) -> dict:
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def _training(folder: Path) -> dict | None:
    path = folder / "train.json"
    if not path.exists():
        return None
    hist = json.loads(path.read_text())
    return {"epochs": len(hist["history"]), "best_epoch": hist["best"]["epoch"],
            "seconds": wall_seconds(hist["history"]), "curve": str(folder / "loss.png")}


def run_afgsa_report(cfg: Config, spp: int = 4, out: str = "reports/afgsa", runs: dict[str, Path] | None = None,
                     crops: int = 4) -> dict:
    runs = runs or default_runs(cfg, spp)
    missing = [str(f) for f in runs.values() if not (f / "model.safetensors").exists()]
    if missing:
        raise TrainError(f"no AFGSA checkpoint in {', '.join(missing)}: train both first (make train MODEL=afgsa "
                         f"SPP={spp}, and again with afgsa.target=gt1)")
    store, device = Store(cfg.store), pick_device(cfg.afgsa.device)
    models = {label: load_model(folder, device)[0] for label, folder in runs.items()}
    keys = store.frames_with(cfg.eval.split)
    if not keys:
        raise TrainError(f"{store.root}: no {cfg.eval.split} frame with gt_clean")
    per_frame, grid = [], []
    for key in keys:
        buffers = store.read(key.scene, key.frame, spp)
        ref, gt1 = (store.read_image(key.scene, key.frame, n, ["color"])[0]["color"] for n in ("gt_clean", "gt1"))
        inputs, radiance = frame_inputs(buffers)
        outs = {label: denoise(m, inputs, radiance, tile=cfg.afgsa.tile, device=device) for label, m in models.items()}
        first = next(iter(outs.values()))
        per_frame.append(_score({"noisy input": buffers["color"], **outs, "GT1": gt1}, ref, cfg.clean.smape_eps,
                                first))
        if len(grid) < crops:
            grid.append((str(key), [buffers["color"], *outs.values(), gt1, ref]))
    names = list(per_frame[0])
    result = {"store": str(cfg.store), "split": cfg.eval.split, "spp": spp, "frames": len(keys),
              "runs": {label: str(f) for label, f in runs.items()},
              "training": {label: _training(f) for label, f in runs.items()},
              "rows": {n: _mean([f[n] for f in per_frame]) for n in names}}
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    _crops(grid, list(runs), out_dir / "afgsa_targets_crops.png")
    (out_dir / "afgsa_targets.json").write_text(json.dumps(result, indent=1) + "\n")
    md = format_markdown(result)
    (out_dir / "afgsa_targets.md").write_text(md)
    print(md)
    return result


def _crops(grid: list, labels: list[str], path: Path) -> None:
    """noisy | each run | GT1 | GT_clean, then ×DIFF_GAIN |first run − second run| on x/(1+x)."""
    rows = []
    for name, imgs in grid:
        diff = [DIFF_GAIN * np.abs(reinhard(imgs[2]) - reinhard(imgs[1]))] if len(labels) >= 2 else []
        rows.append((name, imgs + diff))
    titles = ["noisy", *labels, "GT1", "GT_clean"]
    if len(labels) >= 2:
        titles.append(f"|2nd - 1st run| x{DIFF_GAIN:g}")
    figures.crop_grid(rows, titles, path, reference=len(labels) + 2)


def format_markdown(r: dict) -> str:
    lines = [f"# AFGSA: trained against GT_clean vs against GT1 ({r['spp']} spp, {r['split']} split, "
             f"{r['frames']} frames, scored against GT_clean)", "",
             "| image | PSNR dB (x/(1+x)) | L1 (HDR, [0,6]) | SMAPE | fine-scale energy / GT_clean's | "
             f"PSNR dB against {next(iter(r['runs']))} |", "| --- | --- | --- | --- | --- | --- |"]
    for name, m in r["rows"].items():
        lines.append(f"| {name} | {m['psnr']:.2f} | {m['l1']:.5f} | {m['smape']:.4f} | {m['fine_energy_ratio']:.3f} | "
                     + ("-" if name == next(iter(r["runs"])) else f"{m['psnr_vs_first']:.2f}") + " |")
    lines += ["", "Fine-scale energy: mean squared difference between the x/(1+x) image and its 3x3 box blur, over "
              "GT_clean's (1 = as much pixel-scale variation as GT_clean; GT1's row is its noise). The last column "
              "says how far each image is from the first run's output (two runs of the same target with another "
              "seed show how far apart training alone puts them).", ""]
    for label, t in r["training"].items():
        if t:
            lines.append(f"- {label}: {r['runs'][label]}, {t['epochs']} epochs in {t['seconds']:.0f} s, best epoch "
                         f"{t['best_epoch']}; curve {t['curve']}")
    lines += ["", "Crops (gamma tonemap): afgsa_targets_crops.png"]
    return "\n".join(lines) + "\n"
