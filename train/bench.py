"""Inference time of the diffusion denoiser: 27, 15 and 9 steps (skip 0, 12, 18) at 256² and per megapixel.

    python -m pipeline bench-denoise [--config FILE] [key=value ...]     (also run by make bench)

Uses the trained run of ``--spp`` if there is one, else the base with a fresh (zero) Control
Module: the network's cost is the same either way. Each setting is timed after one warm-up call,
best of ``repeats``; the per-megapixel time is measured on a frame of ``tile``-sized tiles
(2×2 tiles of 256² by default, overlap included), so it includes the tiling overhead.
"""
from __future__ import annotations

import platform
from pathlib import Path

import torch

from pipeline.bench import best_time
from pipeline.config import Config
from pipeline.exr import atomic_write_json

from .data import AUX_CHANNELS
from .model import build, load, run_dir
from .sampler import sample, sample_tiled
from .train import autocast_dtype, pick_device

SKIPS = (0, 12, 18)


def run(cfg: Config, spp: int = 4, side: int = 256, repeats: int = 2, out: str = "reports/bench") -> dict:
    f = cfg.diffusion
    device = pick_device(f.device)
    folder = run_dir(cfg, spp)
    model = load(folder, device)[0] if (folder / "model.json").exists() else build(cfg).to(device).eval()
    ac = autocast_dtype(f.precision, device)
    g = torch.Generator().manual_seed(0)
    noisy = (torch.rand(1, 3, side, side, generator=g) * 2 - 1).to(device)
    aux = torch.rand(1, AUX_CHANNELS, side, side, generator=g).to(device)
    big = 2 * f.tile - f.tile_overlap   # 2x2 tiles
    noisy_big = (torch.rand(1, 3, big, big, generator=g) * 2 - 1).to(device)
    aux_big = torch.rand(1, AUX_CHANNELS, big, big, generator=g).to(device)
    sample(model, noisy[..., :64, :64], aux[..., :64, :64], skip=26, autocast_dtype=ac)   # warm-up
    rows = []
    for skip in SKIPS:
        t = best_time(lambda: sample(model, noisy, aux, skip=skip, autocast_dtype=ac), repeats)
        tb = best_time(lambda: sample_tiled(model, noisy_big, aux_big, tile=f.tile, overlap=f.tile_overlap, skip=skip,
                                        autocast_dtype=ac), 1)
        rows.append({"steps": 27 - skip, "skip": skip, "side": side, "seconds_frame": round(t, 3),
                     "seconds_per_megapixel": round(tb / (big * big / 1e6), 3),
                     "tiled_frame": f"{big}x{big}"})
    result = {"device": str(device), "cuda": torch.cuda.get_device_name(0) if device.type == "cuda" else None,
              "cpus": __import__("os").cpu_count(), "platform": platform.platform(), "threads": torch.get_num_threads(),
              "model": str(folder) if (folder / "model.json").exists() else "base + fresh Control Module",
              "parameters_millions": round(sum(p.numel() for p in model.parameters()) / 1e6, 2),
              "precision": str(ac) if ac else "fp32", "rows": rows}
    lines = [f"Diffusion inference ({result['model']}, {result['parameters_millions']} M parameters, "
             f"{result['device']}{' ' + result['cuda'] if result['cuda'] else ''}, {result['precision']}, "
             f"{result['threads']} threads)", "",
             f"| steps | {side}² frame (s) | per megapixel (s) |", "| --- | --- | --- |"]
    lines += [f"| {r['steps']} | {r['seconds_frame']:.2f} | {r['seconds_per_megapixel']:.2f} |" for r in rows]
    md = "\n".join(lines) + "\n"
    Path(out).mkdir(parents=True, exist_ok=True)
    atomic_write_json(Path(out) / "denoise.json", result)
    (Path(out) / "denoise.md").write_text(md)
    print(md, end="")
    return result
