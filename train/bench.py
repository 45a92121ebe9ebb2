"""Inference time of the diffusion denoiser at 1, 3, 9 and 27 steps: a 128² frame and per megapixel.

    python -m pipeline bench-denoise [--config FILE] [key=value ...]     (also run by make bench)

Times ``train.infer.Denoiser.denoise`` (input encoding, OIDN's base, the sampler) on a synthetic frame,
with the trained run of ``--spp`` (or the spp-conditioned one, else the shipped model). Each setting is
timed after one warm-up call, best of ``repeats``; the per-megapixel time is measured on a 512² frame.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.exr import StoreError, atomic_write_json
from mcdenoise.pipeline.timing import best_time
from mcdenoise.pipeline.versions import machine

from .infer import Denoiser, load_denoiser
from .model import find_run

STEPS = (1, 3, 9, 27)
BIG = 512   # side of the per-megapixel frame


def _frame(side: int, seed: int = 0) -> dict:
    """A synthetic frame with every renderer buffer and its variance, so the network itself runs (an
    RGB-only frame would time the first estimate alone: ``Denoiser`` returns it for such inputs)."""
    rng = np.random.default_rng(seed)
    out = {}
    for b in schema.BUFFERS:
        shape = (side, side, len(b.channels))
        out[b.name] = (rng.gamma(1.0, 0.3, shape) if b.radiance else rng.random(shape)).astype(np.float32)
        out[schema.variance_name(b.name)] = rng.gamma(1.0, 0.05, shape).astype(np.float32)
    out["normal"] = np.repeat(np.array([[[0, 0, 1]]], np.float32), side, 0).repeat(side, 1)
    return out


def _time(den: Denoiser, buffers: dict, steps: int, repeats: int) -> float:
    return best_time(lambda: den.denoise(buffers, spp=4, steps=steps, skip=0), repeats)


def run(cfg: Config, spp: int = 4, side: int = 128, repeats: int = 2, out: str = "reports/bench") -> dict:
    folder = find_run(cfg, spp)
    den = load_denoiser(folder, cfg.diffusion.device)
    device, name = den.device, str(folder)
    small, big = _frame(side), _frame(BIG, 1)
    _time(den, _frame(32, 2), 1, 1)   # warm-up
    rows = []
    for steps in STEPS:
        t = _time(den, small, steps, repeats)
        tb = _time(den, big, steps, 1)
        px = big["color"].shape[0] ** 2
        rows.append({"steps": steps, "side": side, "seconds_frame": round(t, 3),
                     "seconds_per_megapixel": round(tb / (px / 1e6), 3),
                     "tiled_frame": f"{big['color'].shape[1]}x{big['color'].shape[0]}"})
    mach = machine()
    result = {"device": str(device), "machine": mach, "model": name, "formulation": den.formulation.record(),
              "parameters_millions": round(sum(p.numel() for p in den.model.parameters()) / 1e6, 2),
              "precision": "fp32", "rows": rows,
              "estimate_only": den.last_estimate_only}   # True would mean the network never ran
    lines = [f"Diffusion inference ({result['model']}, {result['parameters_millions']} M parameters, "
             f"{result['device']}{' ' + mach['cuda'] if mach.get('cuda') else ''}, {result['precision']}, "
             f"{mach.get('torch_threads')} threads)", "",
             f"| steps | {side}² frame (s) | per megapixel (s) |", "| --- | --- | --- |"]
    lines += [f"| {r['steps']} | {r['seconds_frame']:.3f} | {r['seconds_per_megapixel']:.2f} |" for r in rows]
    md = "\n".join(lines) + "\n"
    Path(out).mkdir(parents=True, exist_ok=True)
    atomic_write_json(Path(out) / "denoise.json", result)
    (Path(out) / "denoise.md").write_text(md)
    print(md, end="")
    return result


def run_oidn(cfg: Config, out: str = "reports/bench", repeats: int = 2, sizes=((128, 128), (1080, 1920))) -> dict:
    """OIDN three ways, per 128² and per 1080p frame: pyoidn with its built-in weights, pyoidn with
    weights we wrote (the oidn_ft run when there is one, else OIDN's own re-exported), and the PyTorch
    twin (``pipeline.oidn_net``) that trains; and the diffusion denoiser on OIDN (``diffusion.base=oidn``)
    at 1 and 3 steps when the config has such a run."""
    import torch

    from mcdenoise.pipeline import oidn, oidn_net
    from mcdenoise.pipeline.runs import run_dir as model_dir

    from .oidn_ft import export_blob, load_run

    folder = model_dir(cfg, "oidn_ft", variant="rt_hdr_alb_nrm")
    if (folder / "model.safetensors").exists():
        net, what = load_run(folder, cfg)[0], str(folder)
    else:
        net, what = oidn_net.load_unet("rt_hdr_alb_nrm"), "OIDN's own weights, re-exported"
    blob = export_blob(net)
    refiner = None
    try:
        run = find_run(cfg, "any")
        refiner = load_denoiser(run, "cpu")
    except StoreError:
        pass
    rows = []
    warm = _frame(32, 4)
    oidn.denoise(warm), oidn.denoise(warm, weights=blob), oidn_net.denoise(net, warm["color"], warm["albedo"],
                                                                           warm["normal"])
    if refiner is not None:
        refiner.denoise(warm, spp=4)
    for h, w in sizes:
        buf = _frame(max(h, w), 3)
        buf = {k: np.ascontiguousarray(v[:h, :w]) for k, v in buf.items()}
        row = {"size": f"{w}x{h}",
               "pyoidn_builtin_s": best_time(lambda: oidn.denoise(buf), repeats),
               "pyoidn_exported_s": best_time(lambda: oidn.denoise(buf, weights=blob), repeats),
               "torch_twin_s": best_time(lambda: oidn_net.denoise(net, buf["color"], buf["albedo"], buf["normal"]),
                                         repeats)}
        if refiner is not None:
            for steps in (1, 3):
                row[f"ours_{steps}step_s"] = best_time(lambda: refiner.denoise(buf, spp=4, steps=steps), 1)
        rows.append({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()})
    mach = machine()
    result = {"weights": what, "refine_run": str(run) if refiner is not None else None, "machine": mach,
              "torch_threads": torch.get_num_threads(), "rows": rows}
    cols = [k for k in rows[0] if k != "size"]
    lines = [f"OIDN and the denoisers on it, seconds per frame (weights: {what}; {mach.get('processor', '?')}, "
             f"{mach.get('cpus', '?')} CPUs, {torch.get_num_threads()} torch threads; best of {repeats})", "",
             "| frame | " + " | ".join(cols) + " |", "| --- |" + " --- |" * len(cols)]
    lines += ["| " + r["size"] + " | " + " | ".join(f"{r[c]:.3f}" for c in cols) + " |" for r in rows]
    md = "\n".join(lines) + "\n"
    Path(out).mkdir(parents=True, exist_ok=True)
    atomic_write_json(Path(out) / "oidn.json", result)
    (Path(out) / "oidn.md").write_text(md)
    print(md, end="")
    return result
