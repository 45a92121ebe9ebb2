"""Seconds per frame of the denoiser, its base and OIDN's own engine, at the sizes users render.

    python -m pipeline bench-denoise [--config FILE] [--device D] [--precision P] [--sizes WxH,...] [key=value ...]
    (also run by make bench, and by the GPU recipe on a lent GPU)

On a synthetic frame with every renderer buffer (so the Control Module runs; an RGB-only frame would time
the base alone), after one warm-up call, best of ``repeats``:

- ``ours``: ``train.infer.Denoiser.denoise`` end to end at the model's sampler steps (encoding the buffers,
  OIDN's aux prefilter, the base, the Control Module, back to HDR) and at 3 steps (the σ layer's);
- ``base``: the same path with the Control Module off: OIDN's final-frame mode run in PyTorch;
- ``ours network`` / ``base network``: the networks alone on inputs already on the device, and ``nhwc``: the
  same on channels-last tensors (the layout of fp16 tensor-core convolutions on a GPU);
- ``oidn_prefilter`` / ``oidn``: OIDN's own engine (pyoidn, on the device OIDN picks) in its final-frame mode
  (the same large network with prefiltered aux) and as usually called, when pyoidn is installed.

- ``averaging_s`` / ``filter_s`` / ``filter_both_s`` (up to 1080p): what ``denoise --sequence`` adds a frame
  (``_time_sequence``): the noisy input averaged over the frames around it, then the temporal filter, causal or
  on both sides.

``ours / oidn_prefilter`` is the price of the Control Module against what a user has. The networks'
arithmetic per megapixel (``network_gflops``) is the floor of ``ours / base`` on any device and engine:
the base's encoder once, then per sampler step its decoder and the Control Module, plus the base's own
decoder for the estimate the strength blends with.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.exr import atomic_write_json
from mcdenoise.pipeline.timing import best_time
from mcdenoise.pipeline.versions import machine

from .infer import load_denoiser
from .model import find_run
from .sampler import sample

CPU_SIZES = "256x256,1920x1080"
SEQUENCE_MAX_PIXELS = 1920 * 1080      # the sequence path's numpy work is timed up to 1080p
GPU_SIZES = "256x256,1920x1080,3840x2160"


def synthetic_frame(h: int, w: int, seed: int = 0) -> dict:
    """Every renderer buffer of one frame and its variance with plausible ranges."""
    rng = np.random.default_rng(seed)
    out = {}
    for b in schema.BUFFERS:
        shape = (h, w, len(b.channels))
        out[b.name] = (rng.gamma(1.0, 0.3, shape) if b.radiance else rng.random(shape)).astype(np.float32)
        out[schema.variance_name(b.name)] = rng.gamma(1.0, 0.05, shape).astype(np.float32)
    out["normal"] = np.broadcast_to(np.array([0, 0, 1], np.float32), (h, w, 3)).copy()
    return out


def parse_sizes(text: str) -> list[tuple[int, int]]:
    """'256x256,1920x1080' → [(256, 256), (1080, 1920)] as (height, width)."""
    try:
        return [(int(t.split("x")[1]), int(t.split("x")[0])) for t in text.split(",")]
    except (IndexError, ValueError):
        raise ValueError(f"--sizes {text!r}: expected WxH[,WxH...], e.g. 256x256,1920x1080") from None


def network_gflops(model, formulation, steps: int, side: int = 64) -> dict:
    """GFLOP per megapixel of the sampler (``ours``, at ``steps``) and of the base alone, counted by
    ``torch.utils.flop_counter`` on a ``side``² input (every layer is a convolution or elementwise, so the
    count scales with the pixels)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    side += -side % model.multiple
    x = torch.zeros(1, model.base.in_channels, side, side)
    cond = torch.zeros(1, model.cond_channels, side, side)
    p = next(model.base.parameters())
    x, cond = x.to(p.device, p.dtype), cond.to(p.device, p.dtype)

    def gflop(fn) -> float:
        with FlopCounterMode(display=False) as counter, torch.no_grad():
            fn()
        return round(counter.get_total_flops() / 1e9 / (side * side / 1e6), 2)
    return {"ours": gflop(lambda: sample(model, x, cond, formulation, steps)), "base": gflop(lambda: model.base(x))}


def measure(model: Path, sizes: list[tuple[int, int]], device: str = "auto", precision: str = "auto",
            repeats: int = 2, sequence: bool = False) -> dict:
    """The timings of the module docstring for the model folder ``model``; a dict with ``rows``. ``sequence``: the
    sequence path's too (CPU numpy, minutes at 1080p: ``bench-denoise`` times it, a GPU lease's recipe does not)."""
    import torch

    from mcdenoise.train import oidn

    den = load_denoiser(model, device, precision=precision)
    dev = den.device
    timed = _timer(dev, repeats)
    m = den.model
    steps = den.formulation.steps
    rows = []
    for h, w in sizes:
        buf = synthetic_frame(h, w)
        row = {"size": f"{w}x{h}", "megapixels": round(h * w / 1e6, 3)}
        _time_denoiser(den, m, steps, buf, timed, row)
        _time_networks(den, m, steps, h, w, timed, row)
        if sequence and h * w <= SEQUENCE_MAX_PIXELS:
            _time_sequence(h, w, buf, row)
        if oidn.available() is None:
            row["oidn_prefilter_s"] = timed(lambda: oidn.denoise(buf, clean_aux=True))
            row["oidn_s"] = timed(lambda: oidn.denoise(buf))
            row["ours_over_oidn_prefilter"] = round(row[f"ours_{steps}step_s"] / row["oidn_prefilter_s"], 2)
        rows.append(row)
    mach = machine()
    return {"model": str(model), "device": str(dev), "precision": den.precision, "machine": mach,
            "torch_threads": torch.get_num_threads(), "repeats": repeats, "rows": rows,
            "gflop_per_megapixel": network_gflops(m, den.formulation, steps),
            "parameters_millions": round(sum(p.numel() for p in m.parameters()) / 1e6, 2)}


def _timer(dev, repeats: int):
    """``timed(fn, n=repeats)``: the best of ``n`` calls of ``fn`` in seconds, after a warm-up call."""
    import torch

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()

    def timed(fn, n=repeats):
        def call():
            fn()
            sync()   # CUDA runs asynchronously: the time must include the kernels fn launched
        call()                          # warm-up: kernels, allocations, autotuning
        return round(best_time(call, n), 4)
    return timed


def _time_sequence(h: int, w: int, buf: dict, row: dict, frames: int = 12) -> None:
    """Add what ``denoise --sequence`` spends a frame besides the denoiser to ``row`` (numpy on the CPU, once each):
    the input averaged over the 7 frames before and the 7 after (``temporal.InputWindow``: 14 reprojections and
    reads, the gate), and the filter along ``frames`` frames, causal and on both sides (``temporal.filtered``);
    a camera sliding sideways over a plane."""
    from mcdenoise.pipeline import motion, temporal

    def view(k):
        pose = np.eye(4)
        pose[0, 3] = 0.002 * k
        return motion.View(motion.Camera(pose, 40.0, w, h), np.full((h, w), 3.0, np.float32), buf["normal"])
    views = [view(k) for k in range(-7, 8)]
    window = temporal.InputWindow(8, gate=2.0, ahead=7)
    kept = window.keep(buf)

    def average():
        window.past = [(kept, v) for v in views[6::-1]]
        window.take(buf, views[7], [(kept, v) for v in views[8:]])
    row["averaging_s"] = round(best_time(average, 1), 4)
    outputs = [(buf["color"], views[k % len(views)]) for k in range(frames)]
    for name, ahead in (("filter_s", 0), ("filter_both_s", 7)):
        row[name] = round(best_time(lambda: list(temporal.filtered(outputs, 0.7, ahead)), 1) / frames, 4)


def _time_denoiser(den, m, steps: int, buf: dict, timed, row: dict) -> None:
    """Add the whole denoiser's seconds on ``buf`` to ``row``: ours at its steps (and 3) and its base alone."""
    row[f"ours_{steps}step_s"] = timed(lambda: den.denoise(buf, spp=4))
    if steps != 3:
        row["ours_3step_s"] = timed(lambda: den.denoise(buf, spp=4, steps=3), 1)
    # Without its Control Module the denoiser runs its base alone.
    control, m.control = m.control, None
    try:
        row["base_s"] = timed(lambda: den.denoise(buf, spp=4))
    finally:
        m.control = control


def _time_networks(den, m, steps: int, h: int, w: int, timed, row: dict) -> None:
    """Add the seconds of the networks alone on random h x w tensors to ``row``, in NCHW and NHWC layouts."""
    import torch

    dev = den.device
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, m.base.in_channels, h + (-h % 16), w + (-w % 16), generator=g).to(dev)
    cond = torch.rand(1, m.cond_channels, *x.shape[-2:], generator=g).to(dev)
    with torch.no_grad(), den.autocast():
        row["ours_network_s"] = timed(lambda: sample(m, x, cond, den.formulation, steps))
        row["base_network_s"] = timed(lambda: m.base(x))
    # The same networks on NHWC tensors, the layout of the GPU's fp16 tensor-core convolutions (OIDN's
    # engine uses its own blocked layouts); the same numbers, checked in tests/test_denoiser.py.
    xl, cl = x.contiguous(memory_format=torch.channels_last), cond.contiguous(memory_format=torch.channels_last)
    m.to(memory_format=torch.channels_last)
    try:
        with torch.no_grad(), den.autocast():
            row["ours_network_nhwc_s"] = timed(lambda: sample(m, xl, cl, den.formulation, steps))
            row["base_network_nhwc_s"] = timed(lambda: m.base(xl))
    finally:
        m.to(memory_format=torch.contiguous_format)


def markdown(result: dict) -> str:
    mach = result["machine"]
    where = mach.get("cuda") or f"{mach.get('processor', '?')}, {result['torch_threads']} torch threads"
    cols = [k for k in result["rows"][0] if k not in ("size", "megapixels")]
    lines = [f"Seconds per frame ({result['model']}, {result['parameters_millions']} M parameters; {result['device']} "
             f"{where}, {result['precision']}; best of {result['repeats']} after a warm-up)", "",
             "| frame | " + " | ".join(cols) + " |", "| --- |" + " ---: |" * len(cols)]
    lines += ["| " + r["size"] + " | " + " | ".join(str(r.get(c, "")) for c in cols) + " |" for r in result["rows"]]
    g = result["gflop_per_megapixel"]
    lines += ["", f"Arithmetic per megapixel: ours {g['ours']} GFLOP, its base {g['base']} GFLOP "
              f"({g['ours'] / g['base']:.2f}×, the floor of ours / base on any engine)."]
    return "\n".join(lines) + "\n"


def run(cfg: Config, spp: int = 4, sizes: str | None = None, device: str | None = None, precision: str = "auto",
        repeats: int = 2, out: str = "reports/bench") -> dict:
    """``measure`` with the config's model for ``spp`` (its run, else the shipped model); writes
    ``denoise.json`` and ``denoise.md`` into ``out``."""
    from mcdenoise.pipeline.config import pick_device
    dev = pick_device(device or cfg.diffusion.device)
    result = measure(find_run(cfg, spp), parse_sizes(sizes or (GPU_SIZES if dev.type == "cuda" else CPU_SIZES)),
                     str(dev), precision, repeats, sequence=True)
    md = markdown(result)
    Path(out).mkdir(parents=True, exist_ok=True)
    atomic_write_json(Path(out) / "denoise.json", result)
    (Path(out) / "denoise.md").write_text(md)
    print(md, end="")
    return result
